"""Every training hyperparameter, with 3DGS's defaults (``paper_preset``).

The CPU and test-scale recipes are the episode presets' (``pipeline.active.config``): one preset
per name, shown value for value in ``conf/splat/<name>.yaml``."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace

from pipeline.bounds import BOOL, FLOAT, INT, bounded, require_bounds


@dataclass(frozen=True)
class DensifyConfig:
    """3DGS adaptive density control (clone / split by screen-space gradient, prune)."""

    start: int = bounded(500, INT, ge=0)                  # first iteration that densifies
    stop: int = bounded(15_000, INT, ge=0)                # last iteration that densifies; 0: none
    interval: int = bounded(100, INT, ge=1)
    grad_threshold: float = bounded(0.0002, FLOAT, gt=0)  # mean NDC-space gradient norm of means2d
    percent_dense: float = bounded(0.01, FLOAT, gt=0)     # clone if max scale <= this * scene extent, else split
    split_count: int = bounded(2, INT, ge=1)
    split_scale_div: float = bounded(1.6, FLOAT, gt=0)    # 0.8 * split_count
    min_opacity: float = bounded(0.005, FLOAT, ge=0, lt=1)
    max_screen_radius: float = bounded(20.0, FLOAT, gt=0)  # px; applied after ``prune_large_after``
    max_world_scale: float | None = bounded(0.1, FLOAT, gt=0, nullable=True)  # * scene extent; after
    # ``prune_large_after``; None: off.
    # 3DGS prunes big Gaussians from its first opacity reset on (iteration 3000 of 30k, a tenth of
    # the run); kept as its own field so a recipe whose resets are off or rescaled keeps that switch
    prune_large_after: int = bounded(3000, INT, ge=0)
    opacity_reset_interval: int = bounded(3000, INT, ge=1)
    opacity_reset_value: float = bounded(0.01, FLOAT, gt=0, lt=1)
    periodic_opacity_reset: bool = bounded(True, BOOL)  # False: only explicit resets (the active loop's policy)
    max_gaussians: int | None = bounded(None, INT, ge=1, nullable=True, usual_max=5_000_000)  # cap; None = unlimited


@dataclass(frozen=True)
class LearningRates:
    means_init: float = bounded(1.6e-4, FLOAT, gt=0)   # * scene extent, decayed exponentially to means_final
    means_final: float = bounded(1.6e-6, FLOAT, gt=0)
    sh0: float = bounded(2.5e-3, FLOAT, ge=0)
    shN: float = bounded(2.5e-3 / 20, FLOAT, ge=0)
    logit_opacities: float = bounded(0.05, FLOAT, ge=0)
    log_scales: float = bounded(5e-3, FLOAT, ge=0)
    quats: float = bounded(1e-3, FLOAT, ge=0)


@dataclass(frozen=True)
class FitConfig:
    iterations: int = bounded(30_000, INT, ge=1, usual_max=300_000)
    sh_degree: int = bounded(3, INT, ge=0, le=3)
    sh_degree_interval: int = bounded(1000, INT, ge=1)  # raise the active SH degree every this many iterations
    ssim_weight: float = bounded(0.2, FLOAT, ge=0, le=1)  # loss = (1 - w) L1 + w (1 - SSIM)
    lr: LearningRates = field(default_factory=LearningRates)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    image_width: int | None = bounded(None, INT, ge=8, nullable=True, usual_max=4096)  # train at this
    # width (None = full resolution)
    init_points: int = bounded(100_000, INT, ge=1, usual_max=10_000_000)  # random init in the scene box
    # when there is no point cloud
    init_opacity: float = bounded(0.1, FLOAT, gt=0, lt=1)
    seed: int = bounded(0, INT, ge=0)
    lr_decay_iterations: int | None = bounded(None, INT, ge=1, nullable=True)  # the means' lr decays over
    # this many (None: iterations)

    def __post_init__(self) -> None:
        require_bounds(self)  # every declared field, the nested lr and densify groups included

    def with_changes(self, **changes) -> "FitConfig":
        return replace(self, **changes)

    def with_overrides(self, overrides: dict) -> "FitConfig":
        """This recipe with ``overrides`` applied: a nested mapping of field names (``{"lr":
        {"means_init": 1e-4}, "densify": {"grad_threshold": 3e-4}, "ssim_weight": 0.3}``).
        ValueError names the dotted key of an unknown field or a value of the wrong type.
        ``iterations`` is not among them: a recipe's length is changed by ``scaled_to``."""
        if "iterations" in overrides:
            raise ValueError("iterations: set the recipe's length with splat.iterations (it rescales "
                             "every schedule), not as a fit override")
        return _overridden(self, overrides, "")

    def density_events(self, step: int) -> tuple[str, ...]:
        """What 3DGS's adaptive density control does after training step ``step`` (1-based) of
        this recipe, in order: ``"densify"`` (clone, split and prune) every ``interval`` steps
        strictly between ``start`` and ``stop``; ``"reset"`` (the periodic opacity reset) every
        ``opacity_reset_interval`` steps before ``stop``, unless off or in the last tenth of the
        run (no time left to recover the opacities)."""
        d = self.densify
        events = ()
        if d.start < step < d.stop and step % d.interval == 0:
            events += ("densify",)
        late = step > 0.9 * self.iterations
        if d.periodic_opacity_reset and step < d.stop and step % d.opacity_reset_interval == 0 and not late:
            events += ("reset",)
        return events

    def density_events_between(self, first: int, last: int) -> list[tuple[int, str]]:
        """``(step, kind)`` of every density event (``density_events``) in ``first..last``
        (inclusive), in order; only the multiples of the two intervals are asked, so a window of a
        billion steps costs what its events do."""
        d = self.densify
        candidates = set()
        for every in (d.interval, d.opacity_reset_interval):  # both >= 1
            candidates.update(range(-(-max(first, 1) // every) * every, last + 1, every))
        return [(step, kind) for step in sorted(candidates) for kind in self.density_events(step)]

    def flat(self) -> dict[str, object]:
        """Every hyperparameter as ``dotted.name -> value`` (what ``with_overrides`` accepts)."""
        return dotted_leaves(asdict(self))

    def first_iterations(self, iterations: int) -> "FitConfig":
        """The first ``iterations`` steps of this recipe, schedules unchanged: densification,
        resets, SH steps and the learning-rate decay keep their iteration numbers (a 3DGS run
        stopped early). A recipe no longer than ``iterations`` is returned as is."""
        if iterations <= 0:
            raise ValueError(f"iterations must be positive, got {iterations}")
        if iterations >= self.iterations:
            return self
        return replace(self, iterations=iterations,
                       lr_decay_iterations=self.lr_decay_iterations or self.iterations)

    def scaled_to(self, iterations: int) -> "FitConfig":
        """The same recipe over ``iterations`` steps: every schedule scales proportionally."""
        if iterations <= 0:
            raise ValueError(f"iterations must be positive, got {iterations}")
        f = iterations / self.iterations
        d = self.densify
        scale = lambda x: max(1, round(x * f))  # noqa: E731
        return replace(self, iterations=iterations, sh_degree_interval=scale(self.sh_degree_interval),
                       densify=replace(d, start=scale(d.start), stop=scale(d.stop),
                                       interval=scale(d.interval),
                                       prune_large_after=scale(d.prune_large_after),
                                       opacity_reset_interval=scale(d.opacity_reset_interval)))


def _overridden(obj, overrides: dict, where: str):
    known = {f.name: f for f in fields(obj)}
    changes = {}
    for key, value in overrides.items():
        name = f"{where}{key}"
        if key not in known:
            raise ValueError(f"{name}: unknown hyperparameter; allowed {sorted(known)}")
        current = getattr(obj, key)
        if is_dataclass(current):
            if not isinstance(value, dict):
                raise ValueError(f"{name}: a group of hyperparameters ({sorted(f.name for f in fields(current))}), "
                                 f"not a value")
            changes[key] = _overridden(current, value, f"{name}.")
        else:
            changes[key] = _typed(name, current, value, str(known[key].type))
    return replace(obj, **changes)


def _typed(name: str, current, value, annotation: str):
    """``value`` as the field's type (an int where a float is expected is fine; None only where
    the annotation allows it); a field that is None now is checked against its annotation."""
    if value is None:
        if "None" not in annotation:
            raise ValueError(f"{name}: may not be null")
        return value
    if current is None:  # e.g. max_gaussians: int | None
        kinds = [k for k in ("bool", "int", "float", "str") if k in annotation.replace("None", "")]
        current = {"bool": False, "int": 0, "float": 0.0, "str": ""}[kinds[0]] if kinds else value
    if isinstance(current, bool) or isinstance(value, bool):
        if not (isinstance(current, bool) and isinstance(value, bool)):
            raise ValueError(f"{name}: expected {type(current).__name__}, got {value!r}")
        return value
    if isinstance(current, float) and isinstance(value, (int, float)):
        return float(value)
    if isinstance(current, int) and isinstance(value, int):
        return value
    raise ValueError(f"{name}: expected {type(current).__name__}, got {value!r}")


def dotted_leaves(data: dict, where: str = "") -> dict[str, object]:
    """A nested mapping's leaves by dotted key (``{"lr": {"sh0": 1}}`` -> ``{"lr.sh0": 1}``)."""
    out: dict[str, object] = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(dotted_leaves(value, f"{where}{key}."))
        else:
            out[f"{where}{key}"] = value
    return out


def paper_preset() -> FitConfig:
    """3DGS defaults: 30k iterations at full resolution, no Gaussian cap."""
    return FitConfig()
