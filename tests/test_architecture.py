"""The rings of the architecture, read off the tree and checked from the imports.

Every module of ``magcal`` belongs to a ring by its folder (see README, Architecture). A module
may import only the rings listed for its own; the lower rings may not touch files, clocks,
ports, threads, signals or plots; a module in no ring fails the test, so a new top-level module
has to be placed before it can land.
"""

from __future__ import annotations

import ast
import functools
import os
import re
import sys
import warnings

ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "magcal")

# ring → the rings its modules may import (their own included)
ALLOWED = {
    "core": {"core"},
    "wire": {"core", "wire"},
    "fit": {"core", "fit"},
    "sim": {"core", "sim"},
    "logic": {"core", "fit", "logic"},
    "diagnose": {"core", "fit", "sim", "diagnose"},
    "recordings": {"core", "wire", "recordings"},
    "devices": {"core", "wire", "sim", "recordings", "devices"},
    "app": {"core", "wire", "fit", "sim", "logic", "diagnose", "recordings", "devices", "app"},
    "cli": {"core", "wire", "fit", "sim", "logic", "diagnose", "recordings", "devices", "app", "cli"},
}
PURE = {"core", "wire", "fit", "sim", "logic", "diagnose"}
FILES = {"os", "pathlib", "shutil", "tempfile", "io", "glob"}
CLOCK = {"time", "datetime"}
PORTS = {"serial", "smbus2", "socket", "select", "fcntl", "termios", "pty", "ctypes", "subprocess", "threading"}
PROCESS = {"signal", "logging", "sys"}
PLOTS = {"matplotlib"}
# what each ring may use of the outside world, beyond pure computation
EFFECTS_ALLOWED = {
    **{ring: set() for ring in PURE},
    "recordings": FILES | CLOCK,
    "devices": FILES | CLOCK | PORTS | {"signal"},  # signal: a child's exit signal, never a handler
    "app": FILES | CLOCK | PORTS | PROCESS | PLOTS,
    "cli": FILES | CLOCK | PORTS | PROCESS | PLOTS,
}
EFFECTS = FILES | CLOCK | PORTS | PROCESS | PLOTS
SIGNAL_HANDLERS = {"app.daemon.daemon", "cli"}
MAX_FUNCTION_LINES = 80  # a function is read at once
MAX_CLASS_LINES = 300
# the rooms still too big, each being rebuilt by its owner; a new one fails the test
KNOWN_TOO_LONG: set[str] = set()
MAX_MODULE_LINES = 600  # a module holds one job; past this it holds several
# the modules still over it, each to be split by its owner; a new one fails the test
KNOWN_TOO_LONG_MODULES: set[str] = set()
TOP_LEVEL = {"": "core", "__main__": "cli"}  # magcal/__init__.py holds only the version


@functools.lru_cache(maxsize=None)
def parsed(path: str) -> ast.Module:
    """The syntax tree of a file, read once for every rule (the rules walk the same files)."""
    return ast.parse(open(path, encoding="utf-8").read())


def modules():
    for dirpath, _, files in os.walk(ROOT):
        for f in sorted(files):
            if f.endswith(".py"):
                path = os.path.join(dirpath, f)
                rel = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
                name = rel[: -len("__init__")].rstrip(".") if rel.endswith("__init__") else rel
                yield name, path


def placed_modules():
    """(name, path, ring) of every module that has a ring (the others fail the first test)."""
    for name, path in modules():
        ring = ring_of(name)
        if ring is not None:
            yield name, path, ring


def ring_of(name: str) -> str | None:
    if name in TOP_LEVEL:
        return TOP_LEVEL[name]
    first = name.split(".")[0]
    return first if first in ALLOWED and "." in name or name in ALLOWED else None


def package_of(name: str, path: str) -> str:
    base = "magcal" + ("." + name if name else "")
    return base if path.endswith("__init__.py") else base.rsplit(".", 1)[0]


def imports_of(name: str, path: str) -> set[str]:
    """Absolute names of everything a module imports (lazy imports inside functions too)."""
    tree = parsed(path)
    pkg = package_of(name, path)
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = pkg.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                mod = f"{base}.{node.module}" if node.module else base
                out |= {f"{mod}.{a.name}" for a in node.names} | {mod}
            else:
                out.add(node.module or "")
    return out


def magcal_ring(imported: str) -> str | None:
    """The ring of an imported magcal name (``magcal.fit.sphere.fit_sphere`` → ``fit``)."""
    parts = imported.split(".")[1:]
    if not parts or parts[0] in ("__version__",):
        return "core"
    return parts[0] if parts[0] in ALLOWED else None


def calls_open(path: str) -> bool:
    tree = parsed(path)
    return any(isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == "open" for n in ast.walk(tree))


def test_every_module_has_a_ring():
    unplaced = [name for name, _ in modules() if ring_of(name) is None]
    assert not unplaced, f"modules in no ring (put them in a ring's folder): {unplaced}"


def test_a_module_in_no_ring_is_refused():
    """The placement rule itself: a new top-level module or folder is not silently accepted."""
    assert ring_of("helpers") is None
    assert ring_of("utils.things") is None
    assert ring_of("fit.sphere") == "fit" and ring_of("app.daemon") == "app"


def test_rings_import_only_the_rings_below_them():
    bad = []
    for name, path, ring in placed_modules():
        for imp in imports_of(name, path):
            if imp == "magcal" or imp.startswith("magcal."):
                target = magcal_ring(imp)
                if target is None or target not in ALLOWED[ring]:
                    bad.append(f"{name} ({ring}) imports {imp}")
    assert not bad, "\n".join(sorted(bad))


def test_lower_rings_touch_no_files_clocks_ports_signals_or_plots():
    bad = []
    for name, path, ring in placed_modules():
        used = {i.split(".")[0] for i in imports_of(name, path)} & EFFECTS
        if used - EFFECTS_ALLOWED[ring]:
            bad.append(f"{name} ({ring}) imports {sorted(used - EFFECTS_ALLOWED[ring])}")
        if ring in PURE and calls_open(path):
            bad.append(f"{name} ({ring}) calls open()")
    assert not bad, "\n".join(sorted(bad))


def test_no_import_cycles():
    graph = {}
    names = {("magcal." + n if n else "magcal") for n, _ in modules()}
    for name, path in modules():
        full = "magcal." + name if name else "magcal"
        deps = set()
        for imp in imports_of(name, path):
            while imp and imp not in names:
                imp = imp.rpartition(".")[0]
            if imp and imp != full and not full.startswith(imp + "."):  # a package's own __init__ is no cycle
                deps.add(imp)
        graph[full] = deps
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for dep in graph.get(node, ()):
            if state.get(dep) == 1:
                cycle = stack[stack.index(dep):] + [dep]
                raise AssertionError("import cycle: " + " → ".join(cycle))
            if dep not in state:
                visit(dep)
        stack.pop()
        state[node] = 2

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(10_000)
    try:  # the limit is put back: every later test would otherwise run with it (PyYAML's and
        # json's refusals of deep input then walk 10 000 frames, seconds a test)
        for node in graph:
            if node not in state:
                visit(node)
    finally:
        sys.setrecursionlimit(limit)


def test_only_the_daemon_and_cli_install_signal_handlers():
    for name, path in modules():
        tree = parsed(path)
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr == "signal" and getattr(node.value, "id", "") == "signal":
                assert name in SIGNAL_HANDLERS or name.startswith("cli."), name


def _too_long(directory: str):
    """``path:name`` of every function over MAX_FUNCTION_LINES and class over MAX_CLASS_LINES
    below ``directory``, with its length (paths relative to the repository)."""
    repo = os.path.dirname(ROOT)
    for dirpath, dirnames, files in os.walk(directory):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        for f in sorted(files):
            if not f.endswith(".py"):
                continue
            path = os.path.join(dirpath, f)
            for node in ast.walk(parsed(path)):
                limit = {ast.FunctionDef: MAX_FUNCTION_LINES, ast.AsyncFunctionDef: MAX_FUNCTION_LINES,
                         ast.ClassDef: MAX_CLASS_LINES}.get(type(node))
                if limit and node.end_lineno - node.lineno + 1 > limit:
                    yield f"{os.path.relpath(path, repo)}:{node.name}", node.end_lineno - node.lineno + 1


def test_no_function_over_80_lines_and_no_class_over_300():
    repo = os.path.dirname(ROOT)
    found = dict(kv for top in ("magcal", "tests", "bench") for kv in _too_long(os.path.join(repo, top)))
    new = {k: v for k, v in found.items() if k not in KNOWN_TOO_LONG}
    assert not new, "too long to read at once (split it into named steps): " + ", ".join(
        f"{k} ({v} lines)" for k, v in sorted(new.items()))
    done = KNOWN_TOO_LONG - set(found)
    if done:
        warnings.warn(f"no longer too long, take them off KNOWN_TOO_LONG: {sorted(done)}")


def test_the_size_limits_are_checked(tmp_path):
    """The rule itself: a planted long function and a planted large class are found, and a
    function of exactly the limit is not."""
    def lines(n):
        return "\n".join(f"    x{i} = {i}" for i in range(n))

    (tmp_path / "rooms.py").write_text(
        f"def long():\n{lines(MAX_FUNCTION_LINES)}\n\n\ndef fine():\n{lines(MAX_FUNCTION_LINES - 1)}\n\n\n"
        f"class Big:\n{lines(MAX_CLASS_LINES)}\n")
    names = {k.rsplit(":", 1)[1] for k, _ in _too_long(str(tmp_path))}
    assert names == {"long", "Big"}



def _long_modules(directory: str):
    """(path relative to the repository, lines) of every module below ``directory`` over
    MAX_MODULE_LINES."""
    repo = os.path.dirname(ROOT)
    for dirpath, dirnames, files in os.walk(directory):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        for f in sorted(files):
            if f.endswith(".py"):
                path = os.path.join(dirpath, f)
                with open(path, encoding="utf-8") as fh:
                    n = sum(1 for _ in fh)
                if n > MAX_MODULE_LINES:
                    yield os.path.relpath(path, repo).replace(os.sep, "/"), n


def test_no_module_over_600_lines():
    repo = os.path.dirname(ROOT)
    found = dict(kv for top in ("magcal", "tests", "bench") for kv in _long_modules(os.path.join(repo, top)))
    new = {k: v for k, v in found.items() if k not in KNOWN_TOO_LONG_MODULES}
    assert not new, "modules doing more than one job (split them, one module per job): " + ", ".join(
        f"{k} ({v} lines)" for k, v in sorted(new.items()))
    done = KNOWN_TOO_LONG_MODULES - set(found)
    if done:
        warnings.warn(f"no longer too long, take them off KNOWN_TOO_LONG_MODULES: {sorted(done)}")


def test_the_module_limit_is_checked(tmp_path):
    """The rule itself: a planted module one line over the limit is found, one at it is not."""
    (tmp_path / "big.py").write_text("x = 0\n" * (MAX_MODULE_LINES + 1))
    (tmp_path / "fine.py").write_text("x = 0\n" * MAX_MODULE_LINES)
    assert [os.path.basename(p) for p, _ in _long_modules(str(tmp_path))] == ["big.py"]

# -- one of each: tail probabilities, ellipsoid solvers ------------------------------------------

TAILS_HOME = "fit.tails"
# what an incomplete beta or gamma function (a t, χ² or F tail) is built from, by hand or from
# scipy.special: used anywhere but the home, it is a second implementation of the home's work
TAIL_PRIMITIVES = {
    "lgamma", "gammaln", "loggamma", "betaln", "betainc", "betaincc", "betaincinv", "betainccinv",
    "gammainc", "gammaincc", "gammaincinv", "gammainccinv", "stdtr", "stdtrit", "chdtr", "chdtrc",
    "chdtri", "fdtr", "fdtrc", "fdtri", "erfc", "erfcinv",
}
# a function named for a tail, or for the continued fraction behind one
_TAIL_NAME = re.compile(r"^_*(log_?)?(t|chi2|f|student|fisher)_(upper_)?(log_?)?(sf|isf|cdf|ppf|quantile)(_\w+)?$|betainc|gammainc|beta_cf|gamma_cf|lentz|continued_fraction")
# today's other ones, each to be moved onto the home by its owner; a new one fails the test
KNOWN_TAILS: set[str] = set()
# a damped normal-equation solve in a loop (Levenberg–Marquardt; Gauss–Newton with a damping
# term) is an iterative least-squares solver: the geometric fit's is the sanctioned one
SOLVES = {"solve", "lstsq", "cho_solve", "solve_triangular", "lu_solve"}
_DAMPING = re.compile(r"^(lam|lambda_?|lmbda|mu|damp\w*|levenberg\w*)$")
SANCTIONED_SOLVERS = {"fit/geometric.py:damped_step"}
# today's second and third ones, to be merged onto the sanctioned one; a new one fails the test
KNOWN_SOLVERS: set[str] = set()


def _name(node) -> str | None:
    return node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else None


def tail_implementations(tree) -> set[str]:
    """Why a module's code computes a tail probability itself: the primitives it names or
    imports, the functions it defines under a tail's name."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            out |= {a.name for a in node.names} & TAIL_PRIMITIVES
            if node.module == "scipy.stats" or (node.module == "scipy" and any(a.name == "stats" for a in node.names)):
                out.add("scipy.stats")
        elif isinstance(node, ast.Import) and any(a.name == "scipy.stats" for a in node.names):
            out.add("scipy.stats")
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _TAIL_NAME.search(node.name):
            out.add(f"def {node.name}")
        elif _name(node) in TAIL_PRIMITIVES:
            out.add(_name(node))
    return out


def damped_solver_loops(tree) -> set[str]:
    """The functions of ``tree`` that solve damped normal equations inside a loop."""
    out: set[str] = set()

    def visit(node, fn: str, in_loop: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                visit(child, child.name, False)
                continue
            if in_loop and isinstance(child, ast.Call) and _name(child.func) in SOLVES and child.args and any(
                    _DAMPING.match(_name(n) or "") for n in ast.walk(child.args[0])):
                out.add(fn)
            visit(child, fn, in_loop or isinstance(child, (ast.For, ast.While)))

    visit(tree, "<module>", False)
    return out


def _one_of_each(found: set[str], known: set[str], what: str) -> None:
    new = found - known
    assert not new, f"a second {what} (use the one that exists): {sorted(new)}"
    done = known - found
    if done:
        warnings.warn(f"no longer a second {what}, take them off the known list: {sorted(done)}")


def test_tail_probabilities_have_one_home():
    found = {}
    for name, path, _ in placed_modules():
        if name != TAILS_HOME:
            why = tail_implementations(parsed(path))
            if why:
                found[name] = why
    new = {k: v for k, v in found.items() if k not in KNOWN_TAILS}
    assert not new, f"tail probabilities computed outside magcal/fit/tails.py (use it): {new}"
    _one_of_each(set(found), KNOWN_TAILS, "tail-probability implementation")


def test_ellipsoid_solvers_are_not_multiplied():
    found = set()
    for name, path, _ in placed_modules():
        rel = os.path.relpath(path, ROOT).replace(os.sep, "/")
        found |= {f"{rel}:{f}" for f in damped_solver_loops(parsed(path))}
    assert SANCTIONED_SOLVERS <= found, "the sanctioned solver is no longer found: is the rule still looking?"
    _one_of_each(found - SANCTIONED_SOLVERS, KNOWN_SOLVERS, "iterative least-squares solver")


def test_the_one_of_each_rules_find_a_planted_second_one():
    """The rules themselves: a hand-written incomplete beta, a tail under its own name, and a
    Levenberg–Marquardt loop are found; a plain solve in a loop and a plain log are not."""
    tree = ast.parse(
        "import math\nimport numpy as np\n\n"
        "def ibeta(x, a, b):\n    return math.lgamma(a + b) - math.lgamma(a) + a * math.log(x)\n\n"
        "def chi2_isf(q, k):\n    return 2.0 * k\n\n"
        "def lm(A, g, x):\n    lam = 1e-3\n    for _ in range(9):\n"
        "        x = x + np.linalg.solve(A + lam * np.eye(3), -g)\n    return x\n\n"
        "def smooth(A, b):\n    for _ in range(3):\n        b = np.linalg.solve(A, b)\n    return math.log(b[0])\n")
    assert tail_implementations(tree) == {"lgamma", "def chi2_isf"}
    assert tail_implementations(ast.parse("from scipy import stats\n")) == {"scipy.stats"}
    assert tail_implementations(ast.parse("from scipy.stats import chi2\n")) == {"scipy.stats"}
    assert damped_solver_loops(tree) == {"lm"}


# -- one name, one meaning: no class name defined twice -------------------------------------------


# the calls that make a class without a class statement (``Decision = Enum("Decision", …)``)
CLASS_FACTORIES = {"Enum", "IntEnum", "StrEnum", "Flag", "IntFlag", "namedtuple", "NamedTuple", "TypedDict",
                   "make_dataclass"}


def _classes_made(node) -> list[str]:
    """The class names ``node`` defines: a ``class`` statement's, or the names a class factory's
    result is assigned to."""
    if isinstance(node, ast.ClassDef):
        return [node.name]
    if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) and _name(node.value.func) in CLASS_FACTORIES:
        return [t.id for t in node.targets if isinstance(t, ast.Name)]
    return []


def class_definitions(directory: str) -> dict[str, list[str]]:
    """Each class name defined below ``directory`` (top-level and nested ``class`` statements,
    and classes made by ``CLASS_FACTORIES``) → where (``path:line``, relative to ``directory``)."""
    out: dict[str, list[str]] = {}
    for dirpath, dirnames, files in os.walk(directory):
        dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
        for f in sorted(files):
            if f.endswith(".py"):
                path = os.path.join(dirpath, f)
                for node in ast.walk(parsed(path)):
                    for name in _classes_made(node):
                        out.setdefault(name, []).append(f"{os.path.relpath(path, directory)}:{node.lineno}")
    return out


def test_no_class_name_is_defined_twice():
    """A name a reader meets in two modules should mean one thing: two classes of one name are
    either one concept built twice (keep one) or two concepts (name each for what it is)."""
    twice = {k: v for k, v in class_definitions(ROOT).items() if len(v) > 1}
    assert not twice, "class names defined more than once in magcal/: " + "; ".join(
        f"{k} ({', '.join(v)})" for k, v in sorted(twice.items()))


def test_a_class_name_defined_twice_is_found(tmp_path):
    """The rule itself: a name defined in two modules (one of them nested in a function), and
    one made both by a class statement and by ``Enum(...)``, are found with both places; names
    defined once are not."""
    (tmp_path / "fit").mkdir()
    (tmp_path / "logic").mkdir()
    (tmp_path / "fit" / "one.py").write_text("class Step:\n    pass\n\n\nclass Alone:\n    pass\n\n\n"
                                             "class Decision:\n    pass\n")
    (tmp_path / "logic" / "two.py").write_text("from enum import Enum\n\n\ndef f():\n    class Step:\n        pass\n"
                                               "    return Step\n\n\nDecision = Enum('Decision', ['A'])\n"
                                               "total = sum([1, 2])\n")
    found = class_definitions(str(tmp_path))
    one, two = os.path.join("fit", "one.py"), os.path.join("logic", "two.py")
    assert {k: v for k, v in found.items() if len(v) > 1} == {
        "Step": [f"{one}:1", f"{two}:5"], "Decision": [f"{one}:9", f"{two}:10"]}
    assert found["Alone"] == [f"{one}:5"] and "total" not in found
