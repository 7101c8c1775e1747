"""The active-reconstruction round loop: fit -> score -> select -> add. Returns records, never logs."""

from pipeline.active.config import EpisodeConfig, cpu_episode, episode_preset, paper_episode, tiny_episode
from pipeline.active.episode import run_episode
from pipeline.active.plan import EpisodeOutline, EpisodePlan
from pipeline.interchange.results import EpisodeResult, FinalMetrics, RoundRecord
from pipeline.active.schedule import Schedule, episode_schedule

__all__ = ["EpisodeConfig", "EpisodeOutline", "EpisodePlan", "EpisodeResult", "FinalMetrics", "RoundRecord", "Schedule",
           "cpu_episode",
           "episode_preset", "episode_schedule",
           "paper_episode", "run_episode", "tiny_episode"]
