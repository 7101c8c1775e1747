"""``gopre-report``: turn a sweep's records into tables and figures.

    gopre-report outputs/demo                      # -> reports/demo/
    gopre-report outputs/table1_global --out reports/table1
    gopre-report outputs/science --reference fisherrf   # paired differences against fisherrf
    gopre-report outputs/science --seeds 0,1,2          # only complete seeds
    gopre-report outputs/table1_global --paper           # beside the paper's Table 1 (paper.md)
    gopre-report outputs/science --paper table2_goal     # the study's goal runs beside Table 2
    gopre-report outputs/science outputs/table1_global --paper table1_global --out reports/t1
                                                         # several sweeps as one table
    gopre-report --mlflow-uri http://host:5000 --experiment table1_global --out reports/table1
    gopre-report outputs/table2_goal outputs/table2_noreset --by-sweep  # the same episodes under two
                                                         # policies: each sweep a setting, paired against the first
    gopre-report outputs/table5_probes --baseline-setting K=1   # every setting against K=1, method by method
    gopre-report outputs/table2_goal --results elsewhere/                # result.json files from anywhere
    gopre-report --results 'runs/**/result.json' --benchmark reports/benchmarks/table2_goal.json

Prints the Markdown tables; writes report.md, table.md, table.tex, figures/*.png, falls.csv (each
episode's worst round-to-round fall of the curve) and runs.csv.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.cli import alias_note, command_name, unwritable
from pipeline.report.report import combine_records, make_report


def with_results(frame, patterns: list[str], benchmarks: list[str], sweeps: list[Path]):
    """``frame`` (or nothing) with the accepted ``--results`` appended as records rows."""
    import pandas as pd

    from pipeline.report.external import external_rows, method_identities
    from pipeline.report.report import in_config_order, with_metrics_version
    known = set() if frame is None else set(frame["config_hash"].dropna())
    first = 0 if frame is None or "job_index" not in frame else int(frame["job_index"].max()) + 1
    extra = external_rows(patterns, benchmarks, sweeps, known, first, method_identities(frame),
                          rescore=RenderScorer(sweeps))
    if extra.empty:
        if frame is None:
            raise ValueError("--results: every result given is already in the reported sweep")
        return frame
    if frame is None:
        return in_config_order(with_metrics_version(extra))
    return in_config_order(pd.concat([frame, with_metrics_version(extra)], ignore_index=True))


class RenderScorer:
    """Scores a result's shipped renders (``pipeline.eval.outside_renders``) against the scene of the
    reported sweep that ran its benchmark (read once per scene and width); None when it ships none.
    Without such a sweep the renders' hashes are all that can be checked, and a line says so."""

    def __init__(self, sweeps: list[Path]):
        self.sweeps, self.scenes = sweeps, {}

    def scene_of(self, doc: dict):
        from pipeline.data.load import load_scene
        from pipeline.experiment.layout import SweepFolder
        b, width = doc["benchmark"], doc["views"].get("image_width")
        for sweep in self.sweeps:
            folder = SweepFolder(sweep if sweep.is_dir() else sweep.parent)
            if not folder.jobs_file.exists():
                continue
            job = next((j for j in folder.read_jobs() if (j.dataset, j.scene) == (b["dataset"], b["scene"])), None)
            if job is not None:
                key = (job.scene_path, width, job.masks)
                if key not in self.scenes:
                    self.scenes[key] = load_scene(job.scene_path, width=width, masks=job.masks)
                return self.scenes[key]
        return None

    def __call__(self, doc: dict, path: Path):
        from pipeline.eval.outside_renders import recompute, shipped_renders
        if shipped_renders(path) is None:
            return None
        scene = self.scene_of(doc)
        if scene is None:
            print(f"{command_name('report')}: note: {path} ships renders, but no reported sweep ran its scene: "
                  "its metrics are taken as the file states", file=sys.stderr)
            return None
        return recompute(doc, path, scene)


def baseline_setting(frame, args) -> str | None:
    """--baseline-setting, else with --by-sweep the first sweep's first setting (config order)."""
    if args.baseline_setting is not None or not args.by_sweep:
        return args.baseline_setting
    final = frame[frame["kind"] == "final"]
    return str(final["setting"].iloc[0]) if not final.empty else None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=command_name("report"), description=__doc__,
                                     epilog=alias_note("report"),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", nargs="*", type=Path,
                        help="a sweep output folder or its records.parquet; several are reported "
                             "as one table (an episode finished in two of them is an error)")
    parser.add_argument("--out", type=Path, default=None, help="default: reports/<sweep name>")
    parser.add_argument("--mlflow-uri", default=None, help="read the runs from MLflow instead")
    parser.add_argument("--experiment", default=None, help="MLflow experiment (= sweep name)")
    parser.add_argument("--seeds", default=None,
                        help="only these seeds, e.g. 0,1,2 (a sweep stopped inside a later seed)")
    parser.add_argument("--reference", default=None,
                        help="method the paired comparisons are against (default: gopre when it ran)")
    parser.add_argument("--by-sweep", action="store_true",
                        help="several sweeps of the same episodes (e.g. one with an override): each sweep is a "
                             "setting named after it, and every method's settings are paired against the first "
                             "sweep's (or --baseline-setting)")
    parser.add_argument("--baseline-setting", default=None, metavar="SETTING",
                        help="pair each method's other settings against this one (final PSNR, curve area)")
    parser.add_argument("--paper", nargs="?", const="auto", default=None, metavar="TABLE",
                        help="also print the sweep beside the paper's table (paper.md): the table the "
                             "sweep's name maps to, or TABLE (table1_global ... table6_pool)")
    parser.add_argument("--results", action="append", default=[], metavar="DIR_OR_GLOB",
                        help="also report these result.json files (a file, a folder searched for them, or a "
                             "glob; repeatable): each must match the benchmark it names, checked against "
                             "--benchmark or the reported sweep's own views, else it is refused naming the field")
    parser.add_argument("--benchmark", action="append", default=[], metavar="FILE",
                        help="benchmark definitions (gopre-data benchmark PRESET --out FILE) the --results "
                             "are checked against; repeatable")
    parser.add_argument("--no-images", action="store_true",
                        help="curves only: no figure made of the scenes' images (qualitative grids with their "
                             "ground truth, uncertainty maps), for data whose license keeps its pictures out "
                             "of a published report")
    parser.add_argument("--allow-mixed", action="store_true",
                        help="report a row whose episodes come from several code versions, plugin versions or "
                             "data fingerprints (refused otherwise, naming the two); each row's identities are "
                             "listed in report.md")
    parser.add_argument("--paper-only", action="store_true",
                        help="with --paper: write only paper.md into --out (no tables, figures, run list)")
    return parser


def _check_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Arguments that do not go together: a usage error before anything is read."""
    if args.paper_only and args.paper is None:
        parser.error("--paper-only goes with --paper")
    if (args.mlflow_uri or args.experiment) and not (args.mlflow_uri and args.experiment):
        parser.error("--mlflow-uri and --experiment go together")
    if not (args.mlflow_uri or args.source or args.results):
        parser.error("give a sweep folder, --results, or --mlflow-uri and --experiment")
    if args.by_sweep and not args.mlflow_uri and len(args.source) < 2:
        parser.error("--by-sweep compares sweeps: give two or more sweep folders")
    if args.benchmark and not args.results:
        parser.error("--benchmark goes with --results")
    if args.seeds:
        try:
            args.seeds = {int(x) for x in args.seeds.split(",")}
        except ValueError:
            parser.error(f"--seeds: expected integers separated by commas, got {args.seeds!r}")


def records_of(args: argparse.Namespace):
    """The records frame to report and the folder it came from: MLflow's runs, the sweep folders,
    the accepted ``--results`` appended, only ``--seeds``; refused when a row mixes identities."""
    if args.mlflow_uri:
        from pipeline.experiment.records import records_from_mlflow  # the tracking edge
        frame, source = records_from_mlflow(args.mlflow_uri, args.experiment), Path(".")
    elif args.source:
        frame, source = combine_records(args.source, by_sweep=args.by_sweep), args.source[0]
    else:
        frame, source = None, Path(".")
    if args.results:
        frame = with_results(frame, args.results, args.benchmark, list(args.source))
    if args.seeds:
        frame = frame[frame["seed"].isin(args.seeds)]
        if frame.empty:
            raise ValueError(f"no records for seeds {sorted(args.seeds)}")
    from pipeline.report.identity import check_rows
    check_rows(frame, args.allow_mixed)
    return frame, source


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    _check_arguments(parser, args)
    try:
        frame, source = records_of(args)
        out = args.out or Path("reports") / str(frame["sweep"].iloc[0])
        problem = unwritable(out, "--out", folder=True)
        if problem:
            raise ValueError(problem)
        if args.paper_only:
            summary = {"out": str(out), "tables": "", "runs": len(frame[frame["kind"] == "final"]),
                       "failed": 0, "figures": {}}
            Path(out).mkdir(parents=True, exist_ok=True)
        else:
            summary = make_report(source, out, frame, args.reference, baseline_setting(frame, args),
                                  images=not args.no_images, allow_mixed=args.allow_mixed)
        if args.paper is not None:
            from pipeline.report.paper import paper_report
            beside = paper_report(frame, None if args.paper == "auto" else args.paper)
            (Path(summary["out"]) / "paper.md").write_text(beside)
    except (FileNotFoundError, ValueError) as err:
        print(f"{command_name('report')}: error: {err}", file=sys.stderr)
        return 1
    print(summary["tables"])
    if args.paper is not None:
        print(beside)
    if args.paper_only:
        print(f"written {summary['out']}/paper.md")
        return 0
    if summary.get("removed_figures"):
        print(f"removed from {summary['out']}/figures what an earlier report there drew and this one does "
              f"not: {', '.join(summary['removed_figures'])}")
    print(f"report written to {summary['out']}/report.md ({summary['runs']} runs, {summary['failed']} failed); "
          f"figures: {', '.join(summary['figures']) or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
