"""``cae-lcd bench``: ``bench.run.main`` (measures this machine, writes the tables into BENCHMARKS.md); prints them.

``bench/`` is not installed with the package (it measures a checkout: ``../shared``, BENCHMARKS.md): where it is
missing the command only says so.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from cae_lcd.core.cli import add_unavailable, api_defaults

__all__ = ["add_parser", "run", "sections_of"]

NOT_INSTALLED = "cae-lcd bench runs in a checkout of the repository (bench/ is not installed with the package)"


def _int_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(s) for s in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def _import_bench() -> Any:
    """``bench.run``: importable from the checkout's root (the working directory: ``bench/`` is not installed)."""
    root = Path.cwd()
    if (root / "bench" / "run.py").is_file() and str(root) not in sys.path:
        sys.path.insert(0, str(root))
    import bench.run as bench_run

    return bench_run


def add_parser(sub: Any) -> None:
    try:
        bench_run = _import_bench()
    except ModuleNotFoundError as err:
        if (err.name or "").split(".")[0] != "bench":
            raise
        add_unavailable(sub, "bench", NOT_INSTALLED, "needs a checkout of the repository")
        return
    defaults = api_defaults(bench_run.main)
    p = sub.add_parser("bench", help="measure speed, memory, index scaling and methods on this machine; "
                                     "write BENCHMARKS.md", description=bench_run.__doc__.split("\n\n")[0])
    p.add_argument("--out", default=defaults["out"], help="Markdown file to update (default %(default)s)")
    p.add_argument("--run-dir", default=defaults["run_dir"], help="folder for runs (default %(default)s)")
    p.add_argument("--quick", action="store_true", help="tiny sizes (< 1 min): checks the command end to end")
    p.add_argument("--sections", help=f"comma-separated subset of {','.join(bench_run.SECTIONS)} "
                                      f"(default: all but training)")
    p.add_argument("--skip-scale", action="store_true", help="leave out the index scaling section")
    p.add_argument("--training-study", action="store_true",
                   help="run only the training study (a few minutes; its own section of the output file)")
    p.add_argument("--mild", action="store_true",
                   help="run only the MILD comparison (bench/mild.py: cae / mild / mild+verify side by side, query "
                        "time at 1k-100k images, the P_recall plot; ~15 min; its own section of the output file)")
    p.add_argument("--data", help="KITTI sequences folder with 00, 07, 90 "
                                  "(default: ../shared/datasets/kitti/sequences)")
    p.add_argument("--budget-s", type=float, default=defaults["budget_s"],
                   help="time budget in seconds; optional parts are skipped to fit (default %(default)s)")
    p.add_argument("--index-memory-gib", type=float, default=defaults["index_memory_gib"],
                   help="largest index built, GiB (default %(default)s)")
    p.add_argument("--index-sizes", type=_int_list,
                   help="comma-separated stored-code counts (default 10000,100000; 10000,100000,1000000 adds "
                        "the million row, ~15 min)")
    p.add_argument("--training-epochs", type=int, default=defaults["training_epochs"],
                   help="epochs for the other-data weights of the training study (default %(default)s)")
    p.set_defaults(func=run)


def sections_of(args: Any) -> tuple[str, ...]:
    """The sections to run: ``--sections`` (default: all but training), ``--training-study`` alone,
    ``--skip-scale`` without ``index``."""
    import bench.run as bench_run

    if args.training_study:
        return ("training",)
    sections = (tuple(s.strip() for s in args.sections.split(",")) if args.sections
                else bench_run.DEFAULT_SECTIONS)
    return tuple(s for s in sections if s != "index") if args.skip_scale else sections


def run(args: Any) -> None:
    import bench.mild as bench_mild
    import bench.run as bench_run

    if args.mild:
        data = Path(args.data).parents[1] if args.data else bench_run.DATA_DIR.parents[1]
        bench_mild.main(data, Path(args.run_dir) / "mild", Path(args.out))
        return
    res = bench_run.main(args.out, args.run_dir, args.quick, sections_of(args), args.data, args.budget_s,
                         args.index_memory_gib, args.index_sizes, args.training_epochs)
    sys.stdout.write(res["head"] + "\n\n" + "\n\n".join(res["markdown"].values()) + "\n")
