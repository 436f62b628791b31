"""The ``gpupro`` command: ``run`` an experiment config, ``fit`` parameters, ``list`` techniques, write ``docs``.

Errors in configs, scene files and images are reported as one line naming the problem (exit code 2),
never as a Python traceback.
"""

from __future__ import annotations

import argparse
import sys


def _parser() -> argparse.ArgumentParser:
    from gpupro import __version__

    parser = argparse.ArgumentParser(prog="gpupro", description="A JAX laboratory for real-time rendering techniques.")
    parser.add_argument("--version", action="version", version=f"gpupro {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="render an experiment config: EXR, PNG preview and report.json")
    fit = commands.add_parser("fit", help="fit parameters of a config to a target image")
    for sub in (run, fit):
        sub.add_argument("config", help="TOML experiment config")
        sub.add_argument("--out", default="out", help="output folder (default: out)")
        sub.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                         help="override a config key, e.g. --set lights.count=64 (repeatable)")
    run.add_argument("--devices", default=None, metavar="all|N",
                     help="render a camera path as one batch sharded over all (or N) devices")
    listing = commands.add_parser("list", help="print the technique catalogue, one technique's page, or a reference table")
    listing.add_argument("technique", nargs="?", help="a technique id: print its reference page")
    what = listing.add_mutually_exclusive_group()
    for flag, text in (("--scenes", "procedural scene names"), ("--passes", "pass names (the techniques)"),
                       ("--buffers", "every buffer with its producers and channels"), ("--config", "every config key")):
        what.add_argument(flag, action="store_true", help=f"print {text}")
    docs = commands.add_parser("docs", help="write docs/reference.md and docs/techniques/<id>.md from the registry")
    docs.add_argument("folder", nargs="?", default="docs", help="output folder (default: docs)")
    return parser


def _list(args) -> None:
    from gpupro import catalogue
    from gpupro.technique import registered

    if args.technique:
        if args.technique not in registered():
            raise ValueError(f"unknown technique {args.technique!r} (known: {', '.join(registered())})")
        print(catalogue.reference_page(args.technique), end="")
    elif args.scenes:
        print(catalogue.scenes_table())
    elif args.buffers:
        print(catalogue.buffers_table())
    elif args.config:
        print(catalogue.config_reference())
    else:
        print(catalogue.format_catalogue())


def _number(value) -> str:
    """A counter for the console: whole numbers with thousands separators, others to 3 digits."""
    return f"{int(value):,}" if float(value).is_integer() else f"{value:.3g}"


def _counter_lines(report: dict) -> list[str]:
    """The report's headline counters (:func:`gpupro.runner.headline_counters`), one line per pass, those
    of the last frame of a camera path."""
    heading = [f"counters of frame {report['frames']}:"] if report["frames"] > 1 else []
    return heading + [f"  {name}: " + ", ".join(f"{counter} {_number(value)}" for counter, value in values.items())
                      for name, values in report["headline_counters"].items()]


def _run(args) -> None:
    from gpupro.runner import files_line, run_experiment

    # sys.stderr as it is now: the functions' defaults were bound when they were imported
    report = run_experiment(args.config, out_dir=args.out, overrides=args.overrides, progress=sys.stderr,
                            devices=args.devices)
    ms = report["frame_ms"]
    devices = f" x{report['devices']}" if report["devices"] > 1 else ""
    print(f"{report['name']}: {report['triangles']} triangles, {report['lights']} lights, {report['resolution']} "
          f"on {report['device']['device_kind']}{devices}: compile {report['compile_s']:.2f} s, "
          f"frame {ms['median']:.1f} ms (median of {report['timed_runs']} runs)")
    for line in _counter_lines(report):
        print(line)
    print(f"wrote {files_line(report)} in {args.out}")


def _fit(args) -> None:
    from gpupro.fit import fit_experiment

    result = fit_experiment(args.config, out_dir=args.out, overrides=args.overrides, progress=sys.stderr)
    print(f"{result['name']}: loss {result['loss'][0]:.3g} -> {result['loss'][-1]:.3g} in {result['steps']} steps")
    print(f"wrote {', '.join(result['outputs'])} in {args.out}")


def main(argv=None) -> int:
    """Entry point of the ``gpupro`` console script; returns the exit code."""
    args = _parser().parse_args(argv)
    try:
        if args.command == "list":
            _list(args)
        elif args.command == "docs":
            from gpupro.catalogue import write_docs

            print(f"wrote {len(write_docs(args.folder))} files under {args.folder}")
        elif args.command == "run":
            _run(args)
        else:
            _fit(args)
    except (ValueError, FileNotFoundError, OSError, RuntimeError) as error:
        print(f"gpupro {args.command}: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
