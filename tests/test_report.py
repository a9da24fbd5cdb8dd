"""``diagnose --report``: a page a person can read, looked at as a person would — opened in a
browser (headless Chromium), its pictures checked for what a reader needs."""

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cli_inproc import run_magcal
from magcal.app.report import Figure, Section, save, write_report
from magcal.diagnose import diagnose
from magcal.recordings.table import load_table

IMAGES = ("coverage.png", "magnitude.png", "directions.png", "time.png", "channels.png", "heldout.png")


def chromium() -> str:
    """The browser, or skip — fail under CI, where .ci/run installs it."""
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        if os.environ.get("CI") == "true":
            pytest.fail("CI=true but chromium is not installed (apt-get install chromium)")
        pytest.skip("chromium is not installed (apt-get install chromium)")
    return found


def browse(page: Path, tmp_path: Path, *what: str, height: int = 9000) -> subprocess.CompletedProcess:
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars",
             f"--user-data-dir={tmp_path / 'chromium-profile'}", f"--window-size=1400,{height}"]
    return subprocess.run([chromium(), *flags, *what, page.as_uri()], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def temperature_report(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    rec = d / "temp.csv"
    assert run_magcal("simulate", "-o", rec, "--seconds", "300", "--temp-swing", "20",
                      "--temp-coef", "0.1,-0.05,0.06").returncode == 0
    p = run_magcal("diagnose", rec, "--report", d / "page")
    assert p.returncode == 0, p.stderr
    return d / "page"


@pytest.mark.slow
@pytest.mark.xdist_group("temperature_report")  # one diagnosis with its report for both (make test -n)
def test_the_page_leads_with_the_calibration_and_captions_every_figure(temperature_report):
    page = (temperature_report / "index.html").read_text()
    assert page.index("The calibration") < page.index("What was found") < page.index("coverage.png")
    for words in ("offset (hard iron)", "± ", "field", "soft iron", "temp_c term", "µT per °C", "temperature_drift"):
        assert words in page
    for image in IMAGES:
        assert (temperature_report / image).stat().st_size > 10_000 and f'src="{image}"' in page
    assert page.count("<figcaption><b>Look for:</b>") == len(IMAGES) and page.count("<b>Found:</b>") == len(IMAGES) + 1
    # nothing is fetched when the page is viewed: every src and href is inside its folder
    assert not re.search(r"""(src|href)=["']?(https?:|//)""", page)
    assert "<canvas" in page and "cloud-data" in page


@pytest.mark.slow
@pytest.mark.xdist_group("temperature_report")
def test_chromium_shows_the_page_with_its_point_cloud_drawn(temperature_report, tmp_path):
    from PIL import Image

    dom = browse(temperature_report / "index.html", tmp_path, "--dump-dom")
    drawn = re.search(r'<canvas id="cloud-canvas"[^>]*data-drawn="(\d+)"', dom.stdout)
    assert drawn and int(drawn.group(1)) > 1000, dom.stdout[-500:]  # the script ran and drew the samples
    shot = tmp_path / "page.png"
    browse(temperature_report / "index.html", tmp_path, f"--screenshot={shot}")
    with Image.open(shot) as im:
        px = np.asarray(im.convert("L"), dtype=float)
    assert px.shape == (9000, 1400)
    top = px[:7000]
    assert top.std() > 30  # pictures and text, not a blank page
    rows_with_ink = np.mean(top.min(axis=1) < 128)
    assert rows_with_ink > 0.5  # the page fills the window: figures, captions, the cloud


@pytest.mark.slow
def test_figures_are_readable_shapes_with_relative_time(tmp_path):
    """A wide log (many channels, unix time) still gives a grid, and time from its start."""
    from PIL import Image

    rng = np.random.default_rng(4)
    rec = tmp_path / "wide.csv"
    assert run_magcal("simulate", "-o", rec, "--seconds", "120", "--temp-swing", "10").returncode == 0
    lines = rec.read_text().splitlines()
    head = lines[0].split(",")
    t = head.index("t")
    extra = [f"ch{k}" for k in range(8)]
    out = [",".join(head + extra)]
    for ln in lines[1:]:
        cells = ln.split(",")
        cells[t] = repr(1739394679.0 + float(cells[t]))  # unix time, as loggers write it
        out.append(",".join(cells + [f"{v:.4f}" for v in rng.normal(size=len(extra))]))
    rec.write_text("\n".join(out) + "\n")
    p = run_magcal("diagnose", rec, "--report", tmp_path / "page")
    assert p.returncode == 0, p.stderr
    with Image.open(tmp_path / "page" / "channels.png") as im:
        w, h = im.size
    assert w <= 1600 and h >= 800  # 10 panels in rows of 3, not one 9724-px strip
    page = (tmp_path / "page" / "index.html").read_text()
    assert "1.739e" not in page and "e+09" not in page


def test_a_clipped_title_is_refused_not_saved(tmp_path):
    from magcal.app.report import _plt

    plt = _plt()
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.set_title("a title far too long to fit on a figure only three inches wide, so it runs off both sides")
    with pytest.raises(ValueError, match="outside the figure"):
        save(fig, tmp_path, "clipped", plt)
    assert not (tmp_path / "clipped.png").exists()


@pytest.mark.slow
def test_more_sections_join_the_page_through_the_hook(tmp_path):
    from magcal.cli import main

    rec = tmp_path / "r.csv"
    assert main(["simulate", "-o", str(rec), "--seconds", "60", "--quiet"]) == 0
    diagnosis = diagnose(load_table(rec))

    def twin(diagnosis, directory, plt):
        fig, ax = plt.subplots(figsize=(6, 3), constrained_layout=True)
        ax.plot(diagnosis.series.t_s, diagnosis.series.field_ut[:, 0])
        ax.set_title("a section of its own")
        return Section("The sensor twin", (Figure(save(fig, directory, "twin", plt), "Twin residual",
                                                  "what to look for", "what was found"),), key="twin")

    page = write_report(diagnosis, tmp_path / "page", sections=[twin, Section("Notes", html="<p>plain</p>")])
    text = page.read_text()
    assert (tmp_path / "page" / "twin.png").exists()
    assert 'href="#twin"' in text and "The sensor twin" in text and "<p>plain</p>" in text
    assert text.index("The samples in 3-D") < text.index("The sensor twin") < text.index("Notes")


@pytest.mark.slow
def test_a_channel_left_out_of_the_tests_is_said_so_not_drawn_as_tested(tmp_path):
    """The same field in raw counts is screened out of the candidates; the channel figure must not
    show it as a panel saying 'nothing found' (it was never tested) and must say why."""
    rec = tmp_path / "sim.csv"
    assert run_magcal("simulate", "-o", rec, "--seconds", "60", "--scale", "1.04,0.97,1.0").returncode == 0
    lines = rec.read_text().splitlines()
    head = lines[0].split(",")
    mx = head.index("mx")
    rows = [line.split(",") for line in lines[1:]]
    with_counts = [",".join(lines[0].split(",") + ["mag_x_counts"])]
    with_counts += [",".join(r + [str(round(float(r[mx]) / 0.3))]) for r in rows]
    rec.write_text("\n".join(with_counts) + "\n")
    p = run_magcal("diagnose", rec, "--report", tmp_path / "page")
    assert p.returncode == 0, p.stderr
    assert "left out    mag_x_counts" in p.stdout
    page = (tmp_path / "page" / "index.html").read_text()
    assert "Not tested, so not drawn: mag_x_counts: a magnetometer reading" in page
    assert "mag_x_counts: nothing found" not in page


@pytest.mark.slow
def test_a_recording_without_time_is_drawn_by_sample_number_not_in_minutes(tmp_path, monkeypatch):
    """A table with no time column is read by sample index; the page must not turn that index
    into seconds or minutes (4960 samples were once shown as '82.7 min')."""
    import magcal.diagnose as library
    from magcal.app.report.views import views_of

    rec = tmp_path / "sim.csv"
    assert run_magcal("simulate", "-o", rec, "--seconds", "100").returncode == 0
    lines = rec.read_text().splitlines()
    cols = [lines[0].split(",").index(c) for c in ("mx", "my", "mz")]
    rec.write_text("\n".join(",".join(line.split(",")[k] for k in cols) for line in lines) + "\n")
    series = load_table(rec)
    assert not series.clock
    made = []  # the diagnosis the command drew its page from: one diagnosis for the views and the page
    monkeypatch.setattr(library, "diagnose", lambda *a, **k: made.append(diagnose(*a, **k)) or made[-1])
    p = run_magcal("diagnose", rec, "--report", tmp_path / "page")
    assert p.returncode == 0, p.stderr
    assert len(made) == 1 and len(made[0].series) == len(series)
    v = views_of(made[0])
    assert v.t_axis == "sample number (the recording has no time)" and v.t[-1] == len(series) - 1
    page = (tmp_path / "page" / "index.html").read_text()
    assert f"over {len(series)} samples (the recording has no time)" in page
    assert " min." not in page and " min<" not in page
    assert "The sample index stands for time" in page and "t_s is time" not in page


def test_the_time_panel_of_a_recording_without_time_is_titled_by_the_sample_index():
    """Without a time column t_s is the sample index: the channel figure names that panel so, as
    the terminal does ("no time column: sample index"), not after a time channel it never had."""
    from dataclasses import replace

    from magcal.app.report import _plt
    from magcal.app.report.figures import _channel_panel
    from magcal.app.report.views import views_of
    from magcal.sim.physics import Physics, Scenario

    s = Scenario(physics=Physics(hard_iron_ut=(12.0, -20.0, 5.0), noise_ut=0.3), seed=6).simulate(600, 20.0).series
    d = diagnose(replace(s, t_s=np.arange(len(s), dtype=float), clock=False))
    plt = _plt()
    fig, ax = plt.subplots()
    said = _channel_panel(ax, d, views_of(d), "t_s", {})
    assert ax.get_title() == said == "sample index: nothing found"
    plt.close(fig)


def test_every_channel_panel_of_a_level_board_shows_its_samples():
    """A board kept level (a drone, a rover) sees the field along a narrow cone. A channel with
    no term in the model is drawn along the direction the recording sees most, so its panel
    holds the samples; drawn along a fixed axis or a rejected estimate's direction it was empty
    (a PX4 log's panels showed no point at all)."""
    from magcal.app.report import _plt
    from magcal.app.report.figures import _channel_panel
    from magcal.app.report.views import views_of
    from magcal.sim.physics import Current, Motion, Physics, Scenario, Temperature

    sc = Scenario(physics=Physics(hard_iron_ut=(12.0, -20.0, 5.0), noise_ut=0.4),
                  motion=Motion("tilt", max_tilt_deg=15.0, period_s=20.0),
                  temperature=Temperature(swing_c=10.0, period_s=60.0), current=Current(level_a=2.0), seed=5)
    d = diagnose(sc.simulate(1500, 50.0).series)  # 30 s: along x, y or the estimate no sample is drawn
    v = views_of(d)
    plt = _plt()
    for c in ("temp_c", "current_a", "t_s"):
        fig, ax = plt.subplots()
        _channel_panel(ax, d, v, c, {})
        assert len(ax.lines[0].get_xdata()) > len(d.series) / 2, c
        plt.close(fig)


@pytest.mark.slow
def test_the_time_figure_marks_the_time_the_diagnosis_located_a_jump_at():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from magcal.app.report.figures import _mark_located
    from magcal.app.report.views import views_of
    from magcal.core.series import Series
    from test_diagnose import _sim

    run = _sim(141)
    t = run.series.t_s + 1000.0  # a logger's clock does not start at zero; the axis does
    d = diagnose(Series(t_s=t, field_ut=run.series.field_ut + np.outer(t >= t[0] + 40.0, [0.45, -0.3, 0.3])))
    said = [x.where["time_s"][0] for x in d.limits if x.effect == "unexplained_structure" and x.where]
    assert said and abs(said[0] - 1040.0) <= 5.0, said
    fig, ax = plt.subplots()
    _mark_located(ax, d, views_of(d))
    drawn = [float(line.get_xdata()[0]) for line in ax.lines]
    plt.close(fig)
    assert drawn == [said[0] - 1000.0]


def test_the_page_draws_the_field_the_json_states(tmp_path):
    """The page's fitted field (the magnitude figure's line, the point cloud's sphere and its
    caption) is the JSON calibration's, not the model's own scale of it (trace W = 3 against the
    JSON's det W = 1: 30.84 against 30.865 µT on this take)."""
    import json

    p = run_magcal("diagnose", Path(__file__).parent / "data" / "lsm9ds1_ckexplorer_every4th.csv",
                   "--json", "--report", tmp_path / "page")
    assert p.returncode == 0, p.stderr
    field = json.loads(p.stdout)["calibration"]["field_ut"]
    page = (tmp_path / "page" / "index.html").read_text()
    cloud = json.loads(re.search(r'<script type="application/json" id="cloud-data">(.*?)</script>', page).group(1))
    assert cloud["field_ut"] == round(field, 3)
    assert f"from the sphere of {field:.2f} µT" in page and f"radius {field:.2f} µT" in page
