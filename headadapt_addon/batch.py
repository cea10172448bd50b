"""Batch entry: ``python -m headadapt_addon.batch COMMAND ...`` or
``blender -b --python headadapt_addon/batch.py -- COMMAND ...``."""

import argparse
import sys


def build_parser():
    """The command-line interface of the batch job."""
    parser = argparse.ArgumentParser(prog="headadapt", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("demo", help="adapt the bundled template onto the bundled sample scan")
    return parser


def main(argv=None):
    """Run one batch command; returns the process exit code."""
    if argv is None:
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    args = build_parser().parse_args(argv)
    if args.command == "demo":
        print("headadapt: the demo needs the template asset, which is not built yet", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
