"""The ``safewbc`` command line."""

from __future__ import annotations

import argparse
import json
import sys


def _cmd_model_info(args) -> int:
    from safewbc_jax.modelinfo import format_info, model_info

    info = model_info()
    print(json.dumps(info) if args.json else format_info(info))
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="safewbc", description=(
        "Safe whole-body task-space control of the humanoid Digit: an inverse-dynamics QP "
        "with acceleration-based exponential control barrier functions."))
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("model-info", help="sizes, mass, loop residual and foot heights of the models")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_model_info)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
