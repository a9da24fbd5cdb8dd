"""``magcal firmware build`` and ``magcal firmware flash --port P``: the sketch an Arduino Uno
runs, built from the sources the package carries (Debian's AVR toolchain and Arduino core, with
the firmware's own Makefile) and flashed through the Uno's bootloader (avrdude, or arduino-cli
where avrdude is not installed). No source tree is needed: from an installed package the build
goes to the user's cache (``magcal.devices.firmware``).
"""

from __future__ import annotations

from ..devices import firmware

HELP = "build the Arduino firmware from the packaged sources, or flash it to a board"


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    b = sub.add_parser("build", help="build the firmware (HEX and ELF); print where they are")
    f = sub.add_parser("flash", help="build, then flash the firmware to the Uno on --port")
    f.add_argument("--port", required=True, metavar="DEVICE", help="the board's serial device, e.g. /dev/ttyACM0")
    for q in (b, f):
        q.add_argument("--ak8963-14bit", action="store_true",
                       help="the variant for an MPU-9250/9255 whose AK8963 runs at 14-bit output")


def run(args) -> int:
    standard, ak8963_14bit = firmware.build_firmware()
    image = ak8963_14bit if args.ak8963_14bit else standard
    if args.action == "build":
        for built in (standard, ak8963_14bit):
            print(f"built {built.hex} ({built.hex.stat().st_size} bytes; ELF {built.elf.name})")
        print(f"flash it: magcal firmware flash --port /dev/ttyACM0{' --ak8963-14bit' if args.ak8963_14bit else ''}")
        return 0
    print(f"flashing {image.hex.name} to {args.port} ...")
    firmware.flash(args.port, image.hex)
    print(f"flashed {args.port}; check it: magcal show --port {args.port}")
    return 0
