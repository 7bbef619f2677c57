"""The ``dst`` command line: ``dst slice`` turns a STEP file into a DST mesh."""

from __future__ import annotations

import argparse
import os
import sys
import time

EXIT_INPUT = 1  # the input file or the geometry is the problem
EXIT_USAGE = 2  # the command line is the problem (argparse uses 2 as well)
EXIT_INTERNAL = 3  # a bug: please report it


def _add_slice_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "slice",
        help="build the DST mesh of a STEP file",
        description="Intersect the exact B-rep with the slicer's planes and write a watertight STL whose "
        "vertex rings lie exactly on those planes.",
    )
    p.add_argument("input", help="STEP file (AP203, AP214, AP242)")
    p.add_argument("-o", "--output", required=True, help="STL file to write")
    p.add_argument("--layer-height", type=float, default=0.2, help="layer height h, mm (default 0.2)")
    p.add_argument(
        "--first-layer-height", type=float, default=None, help="first-layer height h0, mm (default h)"
    )
    p.add_argument(
        "--mode",
        choices=["middle", "inclusive", "exclusive"],
        default="middle",
        help="slicing tolerance: mid-layer planes (default) or Cura's layer-boundary modes",
    )
    p.add_argument("--segment-length", type=float, default=0.8, help="longest ring segment, mm (default 0.8)")
    p.add_argument("--chord-error", type=float, default=0.025, help="largest chord error, mm (default 0.025)")
    p.add_argument(
        "--target-slicer",
        choices=["cura", "prusa"],
        default=None,
        help="write ring heights exactly as this slicer computes its planes",
    )
    p.add_argument("--ascii", action="store_true", help="write ASCII STL instead of binary")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=_cmd_slice)


def _cmd_slice(args: argparse.Namespace) -> int:
    from worker.dst.params import SliceParams  # noqa: PLC0415 - keep `dst --help` fast

    params = SliceParams.parse(
        layer_height=args.layer_height,
        first_layer_height=args.first_layer_height,
        mode=args.mode,
        segment_length=args.segment_length,
        chord_error=args.chord_error,
        target_slicer=args.target_slicer,
    )
    if not os.path.isfile(args.input):
        raise _UserError(f"input file not found: {args.input}")
    out_dir = os.path.dirname(os.path.abspath(args.output))
    if not os.path.isdir(out_dir):
        raise _UserError(f"output directory does not exist: {out_dir}")

    from worker.dst.pipeline import slice_step  # noqa: PLC0415 - OCP takes a second to import

    start = time.perf_counter()
    last = [""]

    def progress(stage: str, frac: float) -> None:
        if not args.quiet and stage != last[0]:
            last[0] = stage
            print(f"[{time.perf_counter() - start:6.1f}s] {stage}", file=sys.stderr, flush=True)

    mesh = slice_step(args.input, params, progress=progress)
    size = mesh.write_stl(args.output, ascii=args.ascii)
    if not args.quiet:
        st = mesh.stats
        print(
            f"wrote {args.output}: {st['triangles']} triangles, {st['planes']} planes, {size} bytes "
            f"in {time.perf_counter() - start:.1f}s",
            file=sys.stderr,
        )
    for w in mesh.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0


class _UserError(Exception):
    code = "invalid_input"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dst", description="Direct Slicing Tessellation of STEP parts.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_slice_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from worker.dst.errors import DstError, InvalidParameters  # noqa: PLC0415

    try:
        return args.func(args)
    except InvalidParameters as exc:
        print(f"dst: error [{exc.code}]: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (DstError, _UserError) as exc:
        print(f"dst: error [{exc.code}]: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("dst: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: one line, unless --debug asks for the traceback
        if args.debug:
            raise
        print(
            f"dst: internal error: {type(exc).__name__}: {exc} (run with --debug for details)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
