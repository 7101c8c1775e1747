"""Beyond the candidate pool: capture simulators, a space of camera poses, and a
derivative-free search of a score over it. The episode's use of them is not wired yet."""

from pipeline.world.pose_space import LookAtShell, pose_coordinates
from pipeline.world.search import SearchBudget, SearchResult, search_poses
from pipeline.world.simulator import GeneratedWorld, TwinWorld, World, train_twin

__all__ = ["GeneratedWorld", "LookAtShell", "SearchBudget", "SearchResult", "TwinWorld", "World",
           "pose_coordinates", "search_poses", "train_twin"]
