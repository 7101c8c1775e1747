"""The active-reconstruction round loop: fit -> score -> select -> add. Returns records, never logs."""

from pipeline.active.config import EpisodeConfig, cpu_episode, episode_preset, paper_episode, tiny_episode
from pipeline.active.episode import EpisodeResult, RoundRecord, run_episode

__all__ = ["EpisodeConfig", "EpisodeResult", "RoundRecord", "cpu_episode", "episode_preset",
           "paper_episode", "run_episode", "tiny_episode"]
