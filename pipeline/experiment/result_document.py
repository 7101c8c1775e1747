"""An episode as the portable ``result.json`` (``pipeline.interchange``'s schema), and a preset's
benchmark definitions: the same ``views`` block in both, built here from the scene.

Written by every finished episode job beside its internal record (``jobs/<hash>/result.json``,
and the MLflow artifact ``benchmark/result.json``); ``gopre-data benchmark`` writes the definitions.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.active.config import EpisodeConfig
from pipeline.active.plan import EpisodePlan
from pipeline.interchange.results import EpisodeResult
from pipeline.data.protocols import ProtocolViews
from pipeline.data.scene import Scene
from pipeline.experiment.spec import Job
from pipeline.interchange.documents import BENCHMARK_SCHEMA, RESULT_SCHEMA, SCHEMA_VERSION
from pipeline.interchange.hashes import file_sha256, pixels_sha256


def benchmark_key(job: Job) -> dict:
    return {"dataset": job.dataset, "scene": job.scene, "protocol": job.protocol["kind"], "seed": job.seed,
            "setting": job.setting}


def views_block(scene: Scene, views: ProtocolViews, width: int | None, data_fingerprint: str = "") -> dict:
    """What a method must use: splits, initial views, pool, test views with the sha256 of each
    ground-truth image file, the budget, the working width and the scene's data fingerprint."""
    test_paths = scene.split(views.test_split).images.paths
    return {**({"data_fingerprint": data_fingerprint} if data_fingerprint else {}),
            "pool_split": views.pool_split, "test_split": views.test_split,
            "initial_ids": list(views.initial_ids), "pool_ids": list(views.pool_ids),
            "probe_ids": list(views.probe_ids), "test_ids": list(views.test_ids), "budget": int(views.budget),
            "image_width": width,
            "test_image_sha256": {str(i): file_sha256(test_paths[i]) for i in views.test_ids},
            "test_image_files": {str(i): _relative(test_paths[i], scene.root) for i in views.test_ids}}


def _relative(path, root) -> str:
    """An image's path relative to the scene folder (absolute when it lies elsewhere)."""
    from pathlib import Path
    try:
        return Path(path).resolve().relative_to(Path(root).resolve()).as_posix()
    except ValueError:
        return str(path)


def benchmark_entry(job: Job, scene: Scene, cfg: EpisodeConfig) -> dict:
    """One (scene, seed) of a preset: the views, and per round the views trained on, the picks it
    asks for and the probe ids drawn for it (seeded by (seed, round), as every episode draws them)."""
    plan = EpisodePlan.of(scene, cfg)
    views = plan.views
    rounds = [{"round": k, "num_views": int(n), "picks": plan.picks(k, cfg.views_per_round),
               "probes": plan.probes(cfg.seed, k)} for k, n in enumerate(plan.schedule.round_views)]
    manifold = cfg.protocol.manifold if cfg.protocol.kind == "goal" else cfg.protocol.probe_manifold
    return {"benchmark": benchmark_key(job), "views": views_block(scene, views, cfg.fit.image_width, job.data_identity or ""),
            "goal_manifold": None if manifold is None else {"up": list(views.up), **manifold},
            "views_per_round": int(cfg.views_per_round), "pool_keep_fraction": float(cfg.pool_keep_fraction),
            "rounds": rounds}


def benchmark_document(preset: str, entries: list[dict], code_version: str, command: str) -> dict:
    return {"schema": BENCHMARK_SCHEMA, "schema_version": SCHEMA_VERSION, "preset": preset, "command": command,
            "code_version": code_version, "entries": entries}


def result_document(job: Job, scene: Scene, plan: EpisodePlan, result: EpisodeResult,
                    renders: torch.Tensor) -> dict:
    """The episode as ``result.json``; ``plan`` the one the episode ran; ``renders`` [T, H, W, 3] are
    the final model's renders of every test view, in ``result.test_ids`` order."""
    views = plan.views
    final = result.final
    pixels = renders.detach().cpu().numpy().astype(np.float64)
    per_image = [{"test_id": int(view), "psnr": float(final.per_view_psnr[k]),
                  "ssim": None if final.per_view_ssim is None else float(final.per_view_ssim[k]),
                  "render_sha256": pixels_sha256(pixels[k])} for k, view in enumerate(result.test_ids)]
    rounds = [{"num_views": r.num_views, "selected": list(r.selected), "psnr": r.test_psnr, "ssim": r.test_ssim,
               "selection_seconds": r.selection_seconds if r.selected else None,
               "selection_cpu_seconds": r.selection_cpu_seconds if r.selected else None,
               "probes": list(r.probes)} for r in result.rounds]
    return {"schema": RESULT_SCHEMA, "schema_version": SCHEMA_VERSION,
            "method": {"name": job.method, "strategy": job.strategy, "options": dict(job.options),
                       "plugin": job.plugin},
            "benchmark": benchmark_key(job), "views": views_block(scene, views, job.episode.fit.image_width, job.data_identity or ""),
            "rounds": rounds,
            "final": {"num_views": result.rounds[-1].num_views, "psnr": final.psnr, "ssim": final.ssim,
                      "lpips": final.lpips, "per_image": per_image},
            "code_version": job.code_version or "unknown", "config_hash": job.config_hash,
            "config": {k: v for k, v in job.to_dict().items() if k not in ("execution",)}}


def benchmark_entries(jobs: list[Job], scenes: dict, scene_key) -> list[dict]:
    """One entry per (dataset, scene, protocol, seed, setting) of ``jobs`` (methods share it);
    ``scenes[scene_key(job)]`` is the job's scene. Two methods that would see different views
    under one key (a method overriding the protocol) are an error naming both."""
    from pipeline.experiment.episode_settings import ConfigError
    entries: dict[tuple, tuple[dict, str]] = {}
    for job in jobs:
        if job.kind != "episode":
            continue
        entry = benchmark_entry(job, scenes[scene_key(job)], job.episode)
        key = tuple(entry["benchmark"].values())
        if key in entries and entries[key][0]["views"] != entry["views"]:
            raise ConfigError(f"methods {entries[key][1]} and {job.method} see different views on {key}: "
                              "a method overrides the protocol; give them separate benchmark files")
        entries.setdefault(key, (entry, job.method))
    return [entry for entry, _ in entries.values()]
