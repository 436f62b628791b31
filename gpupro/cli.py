"""The ``gpupro`` command: ``run`` an experiment config, ``fit`` parameters, ``list`` techniques.

Errors in configs, scene files and images are reported as one line naming the problem (exit code 2),
never as a Python traceback.
"""

from __future__ import annotations

import argparse
import sys


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="gpupro", description="A JAX laboratory for real-time rendering techniques.")
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="render an experiment config: EXR, PNG preview and report.json")
    fit = commands.add_parser("fit", help="fit parameters of a config to a target image")
    for sub in (run, fit):
        sub.add_argument("config", help="TOML experiment config")
        sub.add_argument("--out", default="out", help="output folder (default: out)")
        sub.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                         help="override a config key, e.g. --set lights.count=64 (repeatable)")
    commands.add_parser("list", help="print the technique catalogue")
    return parser


def main(argv=None) -> int:
    """Entry point of the ``gpupro`` console script; returns the exit code."""
    args = _parser().parse_args(argv)
    try:
        if args.command == "list":
            from gpupro.catalogue import format_catalogue

            print(format_catalogue())
        elif args.command == "run":
            from gpupro.runner import run_experiment

            # sys.stderr as it is now: the functions' defaults were bound when they were imported
            report = run_experiment(args.config, out_dir=args.out, overrides=args.overrides, progress=sys.stderr)
            ms = report["frame_ms"]
            print(f"{report['name']}: {report['triangles']} triangles, {report['lights']} lights, "
                  f"{report['resolution'][0]}x{report['resolution'][1]} on {report['device']['device_kind']}: "
                  f"compile {report['compile_s']:.2f} s, frame {ms['median']:.1f} ms (median of {report['timed_runs']} runs)")
            print(f"wrote {', '.join(report['outputs'])} and report.json in {args.out}")
        else:
            from gpupro.fit import fit_experiment

            result = fit_experiment(args.config, out_dir=args.out, overrides=args.overrides, progress=sys.stderr)
            print(f"{result['name']}: loss {result['loss'][0]:.3g} -> {result['loss'][-1]:.3g} in {result['steps']} steps")
            print(f"wrote {', '.join(result['outputs'])} in {args.out}")
    except (ValueError, FileNotFoundError, OSError) as error:
        print(f"gpupro {args.command}: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
