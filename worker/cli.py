"""The ``dst`` command line: ``dst slice`` turns a STEP file into a DST mesh, ``dst report`` measures a mesh."""

from __future__ import annotations

import argparse
import os
import sys
import time

EXIT_INPUT = 1  # the input file or the geometry is the problem
EXIT_USAGE = 2  # the command line is the problem (argparse uses 2 as well)
EXIT_INTERNAL = 3  # a bug: please report it


def _add_slicing_options(p: argparse.ArgumentParser) -> None:
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
    for axis, when in (("x", "first"), ("y", "second"), ("z", "last")):
        p.add_argument(
            f"--rotate-{axis}",
            type=float,
            default=None,
            metavar="DEG",
            help=f"turn the part DEG degrees about {axis} before slicing ({when}): the orientation it is "
            "printed in (default 0; do not turn the DST mesh about x or y in the slicer)",
        )


def _add_report_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--baselines",
        default=None,
        help="comma-separated conventional meshes to compare with, or 'none' (default "
        "occt_fast,occt_high_quality,prusaslicer; also occt_reference, bambu_orca, prusaslicer_high)",
    )
    p.add_argument("--html", default=None, help="also write a self-contained HTML page of the report")
    p.add_argument("--plot", default=None, help="also write the per-layer plot (.svg or .png)")
    p.add_argument(
        "--processes",
        type=_positive_int,
        default=None,
        help="helper processes the report may run at once (default: the CPUs; 1: all in this process)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if not 1 <= n <= 256:
        raise argparse.ArgumentTypeError(f"expected a whole number from 1 to 256, got {text!r}")
    return n


def _add_slice_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "slice",
        help="build the DST mesh of a STEP file",
        description="Intersect the exact B-rep with the slicer's planes and write a watertight STL whose "
        "vertex rings lie exactly on those planes.",
    )
    p.add_argument("input", help="STEP file (AP203, AP214, AP242)")
    p.add_argument("-o", "--output", required=True, help="STL file to write (.3mf: a 3MF file)")
    _add_slicing_options(p)
    p.add_argument("--ascii", action="store_true", help="write ASCII STL instead of binary")
    p.add_argument(
        "--report", default=None, help="also write the deviation report (JSON) of the mesh and the baselines"
    )
    _add_report_options(p)
    p.set_defaults(func=_cmd_slice)


def _add_report_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="measure any mesh against the exact STEP geometry",
        description="Cut MESH (an STL, e.g. your CAD system's export) and the conventional baselines at the "
        "slicer's planes and compare every layer with the exact section of the STEP part. The mesh must "
        "be in the STEP file's coordinates (x, y as exported, turned by --rotate-* if given; it is dropped to "
        "z = 0 like a slicer does).",
    )
    p.add_argument("input", help="STEP file (AP203, AP214, AP242)")
    p.add_argument("mesh", help="STL file to measure (binary or ASCII)")
    p.add_argument("-o", "--output", required=True, help="report JSON to write")
    _add_slicing_options(p)
    _add_report_options(p)
    p.set_defaults(func=_cmd_report)


def _params(args: argparse.Namespace):
    from worker.dst.params import SLICING_FIELDS, SliceParams  # noqa: PLC0415 - keep `dst --help` fast

    return SliceParams.parse(**{name: getattr(args, name) for name in SLICING_FIELDS})


def _check_output(path: str | None) -> None:
    if path is None:
        return
    out_dir = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(out_dir):
        raise _UserError(f"output directory does not exist: {out_dir}")


def _check_report_outputs(args: argparse.Namespace, json_path: str | None) -> None:
    for path in (json_path, args.html, args.plot):
        _check_output(path)
    if args.plot and os.path.splitext(args.plot)[1].lower() not in {".svg", ".png"}:
        raise _UserError(f"--plot must end in .svg or .png: {args.plot}")
    if (args.html or args.plot or args.baselines or args.processes) and not json_path:
        raise _UserError(
            "--html, --plot, --baselines and --processes need --report (the report they belong to)"
        )


def _progress(args: argparse.Namespace, start: float):
    last = [""]

    def progress(stage: str, frac: float) -> None:
        if not args.quiet and stage != last[0]:
            last[0] = stage
            print(f"[{time.perf_counter() - start:6.1f}s] {stage}", file=sys.stderr, flush=True)

    return progress


def _cmd_slice(args: argparse.Namespace) -> int:
    params = _params(args)
    if not os.path.isfile(args.input):
        raise _UserError(f"input file not found: {args.input}")
    _check_output(args.output)
    three_mf = args.output.lower().endswith(".3mf")
    if three_mf and args.ascii:
        raise _UserError("--ascii is for STL output; a .3mf file is always a zip of XML")
    _check_report_outputs(args, args.report)
    if args.report:
        from worker.dst.baselines import parse_baselines  # noqa: PLC0415

        baselines = parse_baselines(args.baselines)

    start = time.perf_counter()
    progress = _progress(args, start)

    def write(mesh) -> None:
        size = mesh.write_3mf(args.output) if three_mf else mesh.write_stl(args.output, ascii=args.ascii)
        if not args.quiet:
            st = mesh.stats
            print(
                f"wrote {args.output}: {st['triangles']} triangles, {st['planes']} planes, {size} bytes "
                f"in {time.perf_counter() - start:.1f}s",
                file=sys.stderr,
            )

    if args.report:
        from worker.dst.report import slice_and_report  # noqa: PLC0415 - OCP takes a second to import

        _, report = slice_and_report(
            args.input,
            params,
            baselines=baselines,
            progress=progress,
            processes=args.processes,
            on_mesh=write,
        )
        _write_report(args, report, args.report)
    else:
        from worker.dst.pipeline import slice_step  # noqa: PLC0415

        mesh = slice_step(args.input, params, progress=progress)
        write(mesh)
        for w in mesh.warnings:
            print(f"warning: {w}", file=sys.stderr)
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    params = _params(args)
    for path in (args.input, args.mesh):
        if not os.path.isfile(path):
            raise _UserError(f"input file not found: {path}")
    _check_report_outputs(args, args.output)
    from worker.dst.baselines import parse_baselines  # noqa: PLC0415
    from worker.dst.report import MeshInput, build_report  # noqa: PLC0415
    from worker.dst.step_io import read_step  # noqa: PLC0415
    from worker.dst.stl_io import read_stl  # noqa: PLC0415

    baselines = parse_baselines(args.baselines)
    start = time.perf_counter()
    progress = _progress(args, start)
    progress("reading STEP and mesh", 0.0)
    vertices, triangles = read_stl(args.mesh)
    part = read_step(args.input)
    mesh = MeshInput(
        os.path.basename(args.mesh), "input", vertices, triangles, None, f"read from {args.mesh}"
    )
    report = build_report(
        part,
        params,
        file_name=args.input,
        meshes=[mesh],
        baselines=baselines,
        progress=progress,
        processes=args.processes,
    )
    _write_report(args, report, args.output)
    return 0


def _write_report(args: argparse.Namespace, report, json_path: str) -> None:
    from worker.dst.render import write_files  # noqa: PLC0415

    write_files(report, json_path=json_path, html_path=args.html, plots=(args.plot,) if args.plot else ())
    if not args.quiet:
        print(_summary_table(report), file=sys.stderr)
        print(f"wrote {', '.join(p for p in (json_path, args.html, args.plot) if p)}", file=sys.stderr)
    for w in report.warnings:
        print(f"warning: {w}", file=sys.stderr)


def _summary_table(report) -> str:
    def f(x):
        return "-" if x is None else f"{x:.3g}"

    lines = [
        f"{'mesh':22s} {'triangles':>10s} {'max vertex_dev':>15s} {'max chord_dev':>14s} {'p95 chord_dev':>14s}"
    ]
    for m in report.meshes:
        s = m.summary
        lines.append(
            f"{m.name[:22]:22s} {m.triangles:10d} {f(s.max_vertex_dev):>15s} {f(s.max_chord_dev):>14s} "
            f"{f(s.p95_chord_dev):>14s}"
        )
    return "\n".join(lines)


def _add_service_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="run the REST service (API and workers)",
        description="Start the API and, unless --no-worker, a worker with its job processes. By default "
        "everything is embedded: an SQLite broker and job store and artifacts under ./dst-data "
        "(DST_DATA_DIR). Settings: DST_* environment variables (see the README).",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.add_argument(
        "--workers", type=int, default=None, help="jobs run at once on this machine (default: half the cores)"
    )
    p.add_argument("--no-worker", action="store_true", help="API only (workers run elsewhere: `dst worker`)")
    p.set_defaults(func=_cmd_serve)
    w = sub.add_parser(
        "worker",
        help="run a worker only (scale-out)",
        description="Take jobs from the broker (DST_BROKER_URL) and run each in a killable process.",
    )
    w.add_argument("--concurrency", type=int, default=None, help="jobs at once (default: half the cores)")
    w.set_defaults(func=_cmd_worker)


def _add_remote_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "remote",
        help="slice on a running dst-service (HTTP)",
        description="Upload a STEP file to a dst-service, wait for its job and download the DST mesh "
        "(and, with --report/--html, its deviation report).",
    )
    p.add_argument("input", help="STEP file")
    p.add_argument("-o", "--output", required=True, help="STL file to write (.3mf: a 3MF file)")
    p.add_argument(
        "--server",
        default=os.environ.get("DST_SERVER", "http://127.0.0.1:8000"),
        help="service URL (default $DST_SERVER or http://127.0.0.1:8000)",
    )
    _add_slicing_options(p)
    p.add_argument("--baselines", default=None, help="report baselines (comma-separated) or 'none'")
    p.add_argument("--report", default=None, help="also download the report JSON")
    p.add_argument("--html", default=None, help="also download the report page")
    p.set_defaults(func=_cmd_remote)


def _cmd_remote(args: argparse.Namespace) -> int:
    import httpx  # noqa: PLC0415

    from app.client import DstClient, DstError  # noqa: PLC0415
    from worker.dst.params import SLICING_FIELDS  # noqa: PLC0415

    if not os.path.isfile(args.input):
        raise _UserError(f"input file not found: {args.input}")
    for path in (args.output, args.report, args.html):
        _check_output(path)
    params = {name: getattr(args, name) for name in SLICING_FIELDS} | {"baselines": args.baselines}
    try:
        with DstClient(args.server) as c:
            job = c.submit(args.input, **params)
            print(f"job {job['id']} {'(reused)' if job['reused'] else ''}", file=sys.stderr)
            for _event, state in c.events(job["id"]):
                print(f"  {state['progress']:5.0%} {state['stage']}", file=sys.stderr)
            job = c.wait(job["id"])
            c.download_mesh(job["id"], args.output)
            failed = (job.get("result") or {}).get("report_error")
            if not failed:
                if args.report:
                    c.download(job["id"], "report", args.report)
                if args.html:
                    c.download(job["id"], "report.html", args.html)
    except DstError as exc:
        print(f"dst: error [{exc.code}]: {exc.message}", file=sys.stderr)
        return EXIT_INPUT if exc.status in (413, 422) or exc.status == 200 else EXIT_INTERNAL
    except httpx.HTTPError as exc:
        print(f"dst: error [unreachable]: cannot talk to {args.server}: {exc}", file=sys.stderr)
        return EXIT_INTERNAL
    for w in (job.get("result") or {}).get("warnings", []):
        print(f"warning: {w}", file=sys.stderr)
    print(f"wrote {args.output}", file=sys.stderr)
    if failed:
        what = f"the deviation report could not be made [{failed['code']}]: {failed['message']}"
        if args.report or args.html:
            print(f"dst: error [report_failed]: {what}", file=sys.stderr)
            return EXIT_INPUT
        print(f"warning: {what}", file=sys.stderr)
    return 0


def _default_concurrency() -> int:
    return max(1, (os.cpu_count() or 2) // 2)


def _settings_or_exit():
    from pydantic import ValidationError  # noqa: PLC0415

    from worker.settings import get_settings  # noqa: PLC0415

    try:
        settings = get_settings()
    except ValidationError as exc:
        msgs = "; ".join(str(e["msg"]).removeprefix("Value error, ") for e in exc.errors())
        raise _UserError(f"invalid settings: {msgs}") from None
    settings.ensure_dirs()
    return settings


def _worker_argv(concurrency: int, queue: str) -> list[str]:
    import socket  # noqa: PLC0415

    return [
        "worker",
        "--pool=threads",  # each job runs in a process of its own (sandbox); the pool only supervises
        f"--concurrency={concurrency}",
        f"--queues={queue}",
        f"--hostname=dst-{os.getpid()}@{socket.gethostname()}",
        "--without-gossip",
        "--without-mingle",
        "--loglevel=INFO",
    ]


def _share_cpus_between_jobs(concurrency: int) -> None:
    """Unless set, let each job's report fork as many helpers as it has CPUs to itself."""
    from worker.dst.forked import usable_cpus  # noqa: PLC0415

    os.environ.setdefault("DST_REPORT_PROCESSES", str(max(1, usable_cpus() // concurrency)))


def _cmd_worker(args: argparse.Namespace) -> int:
    concurrency = args.concurrency or _default_concurrency()
    _share_cpus_between_jobs(concurrency)
    settings = _settings_or_exit()
    from worker.queue import app  # noqa: PLC0415

    app.worker_main(_worker_argv(concurrency, settings.queue))
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    import signal  # noqa: PLC0415
    import subprocess  # noqa: PLC0415

    import uvicorn  # noqa: PLC0415

    settings = _settings_or_exit()
    worker = None
    if not args.no_worker:
        concurrency = args.workers or _default_concurrency()
        worker = subprocess.Popen(
            [sys.executable, "-m", "worker.cli", "worker", f"--concurrency={concurrency}"],
            start_new_session=False,
        )
    # Jobs left running by a service that was killed: re-run or fail them before serving.
    from worker.queue import enqueue, store  # noqa: PLC0415
    from worker.recovery import recover  # noqa: PLC0415

    for job_id, action in recover(store(), settings, enqueue):
        print(f"dst: job {job_id} was interrupted: {action}", file=sys.stderr)

    # uvicorn shuts down gracefully on SIGTERM, then raises the signal again with the handler it
    # found: by default that ends this process at once, leaving the worker running on its own. This
    # handler turns it into an exception instead, so the worker is stopped below.
    def _terminated(signum, frame):
        raise SystemExit(0)

    signal.signal(signal.SIGTERM, _terminated)
    try:
        uvicorn.run(
            "app.main:app", host=args.host, port=args.port, log_level="info", timeout_graceful_shutdown=5
        )
    except KeyboardInterrupt:
        pass
    finally:
        if worker is not None and worker.poll() is None:
            worker.send_signal(signal.SIGTERM)
            try:
                worker.wait(20)
            except subprocess.TimeoutExpired:
                worker.kill()
    return 0


class _UserError(Exception):
    code = "invalid_input"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dst", description="Direct Slicing Tessellation of STEP parts.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_slice_parser(sub)
    _add_report_parser(sub)
    _add_service_parsers(sub)
    _add_remote_parser(sub)
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
