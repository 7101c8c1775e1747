"""The Hydra room of job making: the composed config (a DictConfig) turned into plain data once, its
interpolations resolved (an error names the key), and handed to ``resolution.resolve_jobs``. Nothing
past this module sees OmegaConf: the jobs' spine is ``spec`` (the record and its hash),
``episode_settings`` (its sections as the core's dataclasses) and ``resolution`` (the sweep's jobs).
"""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.resolution import resolve_jobs
from pipeline.experiment.spec import Job


def _container(cfg: DictConfig, key: str):
    try:
        return OmegaConf.to_container(cfg[key], resolve=True)
    except Exception as err:  # interpolation and resolver errors name the key themselves
        raise ConfigError(f"{key}: {err}") from None


def plain_config(cfg: DictConfig) -> dict:
    """The composed config as plain data, section by section (a bad interpolation names its key)."""
    return {str(key): _container(cfg, str(key)) if OmegaConf.is_config(cfg[key]) else cfg[key] for key in cfg}


def expand_jobs(cfg: DictConfig) -> list[Job]:
    """Every job of the sweep, validated, in a deterministic order (``resolution.resolve_jobs``)."""
    return resolve_jobs(plain_config(cfg))
