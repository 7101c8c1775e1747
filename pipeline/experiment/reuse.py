"""Another output folder's finished jobs, taken into this one only when asked (``reuse_from``).

A sweep decides what is done from its own folder (its records, and the tracking store's runs of this
``output_dir``): a new folder recomputes, even on a tracking server another folder filled. To build
on another folder's results instead, name it: ``reuse_from=[DIR, ...]``. Before anything runs, each
job of this sweep that is not finished here and is finished in a named folder (same config hash: the
same computation on the same data, ``spec.config_hash``) is copied in, the first named folder first:

- its job folder (``jobs/<hash>``: result, artifacts, model, log, starts, round images; not its
  resume checkpoint), copied before its records rows, so a kill in between leaves a folder without
  rows (the job is then reused or run again at the next launch), never rows without files;
- its records rows, unchanged (their code version, worker and run id: the report still tells code
  versions apart and refuses to average them into one row), plus ``reused_from`` naming the folder.

The launch then treats them as finished here, and replays them into the tracking store as runs of
this folder (``replay``), as for any finished job the store lacks.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.layout import SweepFolder
from pipeline.experiment.records import RecordsFile
from pipeline.experiment.spec import Job

REUSED_FROM = "reused_from"  # the records column: the folder a reused job's rows came from


@dataclass(frozen=True)
class Reused:
    """The jobs taken from one folder (config hashes, in that folder's records order)."""

    source: Path
    hashes: list[str]


def source_problems(sources: list[Path], output_dir: Path) -> list[str]:
    """One line per named folder that cannot be reused from (said before any work)."""
    problems = []
    for source in sources:
        if source.resolve() == output_dir.resolve():
            problems.append(f"reuse_from: {source} is this sweep's own output_dir")
        elif not SweepFolder(source).records_file.exists():
            problems.append(f"reuse_from: {source} has no {SweepFolder(source).records_file.name}: not an output "
                            "folder, or no job of it finished")
    return problems


def reuse_finished(jobs: list[Job], sources: list[Path], output_dir: Path, records: RecordsFile) -> list[Reused]:
    """Copy into ``output_dir`` every job of ``jobs`` finished in one of ``sources`` and not here
    (see the module's text); what was taken, per folder."""
    problems = source_problems(sources, output_dir)
    if problems:
        raise ConfigError("\n".join(problems))
    wanted = {j.config_hash for j in jobs} - records.finished_hashes()
    here = SweepFolder(output_dir)
    taken = []
    for source in sources:
        theirs, folder = RecordsFile(source), SweepFolder(source)
        found = [h for h in theirs.finished_versions() if h in wanted and folder.job(h).result_file.exists()]
        if not found:
            continue
        for config_hash in found:  # the files first, then the rows
            shutil.copytree(folder.job(config_hash).path, here.job(config_hash).path, dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns(folder.job(config_hash).checkpoint_dir.name))
        rows = theirs.frame[theirs.frame["config_hash"].isin(found)]
        records.add([{**row, REUSED_FROM: str(source.resolve())} for row in rows.to_dict("records")])
        wanted -= set(found)
        taken.append(Reused(source, found))
    return taken
