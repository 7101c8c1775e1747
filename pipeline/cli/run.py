"""``gopre-run`` (also installed as ``pipeline-run``, the old name, an alias for one release): the Hydra app over ``run_sweep``.

    gopre-run experiment=demo
    gopre-run experiment=table1_global data_root=/data splat=cpu executor.address=auto
    gopre-run experiment=science plan=true      # the job table and an estimate; starts nothing
    gopre-run experiment=demo tracking_sync=true  # replay runs a down tracking server missed

The exit status is 0 when every job finished; 3 when some failed (the summary line says how many,
each failed job's line names its error and traceback.txt); 2 on a config error (nothing
started); 1 on a crash of the driver itself; 130 after Ctrl-C (SIGINT), 143 after SIGTERM: running jobs are
cancelled, their MLflow runs marked KILLED, and the same command resumes them from their last
round checkpoint.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from pipeline.cli import command_name
from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.build import expand_jobs, plain_config
from pipeline.experiment.interrupt import SweepInterrupted, install_stop_handlers
from pipeline.experiment.plan import hyperparameter_text, plan_jobs, plan_text, schedule_text, slots
from pipeline.experiment.schema import config_warnings
from pipeline.experiment.sweep import run_sweep, sync_tracking, validate_sweep
from pipeline.experiment.tracking import mlflow_runs_hint

CONF_DIR = Path(os.environ.get("GOPRE_CONF", Path(__file__).resolve().parents[2] / "conf"))


def data_dir(sub: str, *, _root_: DictConfig) -> str:
    """``${data_dir:blender}`` -> <data_root>/blender; data_root from the command line or GOPRE_DATA."""
    root = _root_.get("data_root")
    if root in (None, "", "None"):
        raise ConfigError(f"data_root is not set (needed for {sub!r}): pass data_root=/path/to/datasets "
                          "or set GOPRE_DATA")
    return str(Path(str(root)) / sub)


def hydra_folder(output_dir: str) -> str:
    """``${hydra_folder:${output_dir}}``: where Hydra keeps its run files, <output_dir>/hydra; a
    temporary folder when output_dir cannot be written, so that the sweep itself refuses it in one
    line (``sweep.writable_folder``) instead of Hydra failing with a traceback before it starts."""
    folder = Path(output_dir) / "hydra"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        return str(folder)
    except OSError:
        import tempfile
        return str(Path(tempfile.gettempdir()) / "gopre-hydra")


def register_resolvers() -> None:
    if not OmegaConf.has_resolver("data_dir"):
        OmegaConf.register_new_resolver("data_dir", data_dir)
    if not OmegaConf.has_resolver("hydra_folder"):
        OmegaConf.register_new_resolver("hydra_folder", hydra_folder)


register_resolvers()


JOBS_FAILED = 3  # apart from a config error (2), a crash (1) and a stop signal (128 + N)


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def main(cfg: DictConfig) -> None:
    if HydraConfig.get().mode == RunMode.MULTIRUN:
        print(f"{command_name('run')}: config error: -m / --multirun would launch several sweeps into one output "
              "folder; give the values inside one sweep instead, e.g. 'method=[gopre,random]' or "
              "+sweep.protocol.probes=[5,10]", file=sys.stderr)
        sys.exit(2)
    if cfg.get("plan"):
        try:
            jobs = expand_jobs(cfg)
        except ConfigError as err:
            print(f"{command_name('run')}: config error: {err}", file=sys.stderr)
            sys.exit(2)
        try:  # the data as a real launch checks it (a scene still to be generated is not read)
            validate_sweep([j for j in jobs if not (j.generate and not (
                Path(j.scene_path) / "transforms_test.json").exists())],
                bool(cfg.get("validate_images", True)))
        except ConfigError as err:
            print(f"{command_name('run')}: config error: {err}", file=sys.stderr)
            sys.exit(2)
        executor = OmegaConf.to_container(cfg.executor, resolve=True)
        assert isinstance(executor, dict)  # a config group: a mapping
        print(hyperparameter_text(jobs) + "\n")
        print(schedule_text(jobs) + "\n")
        print(plan_text(str(cfg.name), plan_jobs(jobs, Path(str(cfg.output_dir))), slots(executor, jobs),
                        config_warnings(plain_config(cfg))))
        return
    if cfg.get("tracking_sync"):
        try:
            sync_tracking(cfg)
        except ConfigError as err:
            print(f"{command_name('run')}: config error: {err}", file=sys.stderr)
            sys.exit(2)
        return
    install_stop_handlers()  # Ctrl-C / SIGTERM: a clean stop with exit status 128 + signal
    try:
        summary = run_sweep(cfg)
    except ConfigError as err:
        print(f"{command_name('run')}: config error: {err}", file=sys.stderr)
        sys.exit(2)
    except SweepInterrupted as stop:
        sys.exit(stop.exit_status)
    print(f"[{summary.name}] finished {summary.finished}, failed {summary.failed}, skipped {summary.skipped} "
          f"of {summary.jobs} jobs in {summary.seconds:.0f} s; records: {summary.output_dir}/records.parquet"
          + (f"; MLflow: {summary.tracking_uri}" if summary.tracking_uri else ""), flush=True)
    hint = mlflow_runs_hint(summary.tracking_uri, summary.experiment_id)
    if hint:
        print(hint, flush=True)
    if summary.failed:
        sys.exit(JOBS_FAILED)


if __name__ == "__main__":
    main()
