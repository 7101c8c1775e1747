"""Where a job's scene is: where it ran, or under another data root (a sweep copied to another
machine), read at the episode's image width. The viewer and ``gopre-eval --sweep`` use it."""

from __future__ import annotations

from pathlib import Path

from pipeline.data.load import load_scene
from pipeline.data.scene import Scene
from pipeline.experiment.spec import Job


def scene_candidates(job: Job, result: dict | None, scene: str | None = None,
                     data_root: str | None = None) -> list[str]:
    """Where the job's scene may be: ``scene`` (given), under ``data_root`` (as <root>/<scene> or
    <root>/<dataset folder>/<scene>, for a sweep copied to another machine), then where it ran."""
    if scene is not None:
        return [str(scene)]
    tried = []
    if data_root is not None:
        ran = Path(job.scene_path)
        tried += [str(Path(data_root) / ran.name), str(Path(data_root) / ran.parent.name / ran.name)]
    if result and result.get("scene"):
        tried.append(result["scene"])
    return tried + [job.scene_path]


def scene_of(job: Job, result: dict | None, scene: str | None = None,
             data_root: str | None = None) -> Scene:
    """The scene the job ran on, read at the episode's image width."""
    width = job.episode.fit.image_width
    tried = scene_candidates(job, result, scene, data_root)
    for path in tried:
        if Path(path).exists():
            return load_scene(path, width=width, masks=job.masks)
    raise ValueError(f"the scene of job {job.config_hash} is not here: tried {', '.join(tried)} "
                     "(pass --scene PATH, or --data-root for a sweep copied from another machine)")
