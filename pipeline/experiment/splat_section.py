"""The ``splat`` config section: every hyperparameter of an episode preset, shown in YAML.

``conf/splat/<preset>.yaml`` lists the preset's values (``pipeline.active.config`` defines them, one
preset per name; ``tests/test_splat_section.py`` checks that the YAML and the preset agree value for
value). A job does not carry the whole listing: ``job_form`` reduces the composed section to what
differs from its preset, the form jobs have always been hashed in, so every finished sweep still
resumes under the same config hash:

- ``iterations, image_width, max_gaussians, epochs_per_view, curve_test_views``: null when equal
  to the preset's value (null has always meant "the preset's");
- ``fit``: only the hyperparameters whose value differs from the preset's recipe, omitted when
  none does. A changed one is taken as written; the others keep the preset's schedule, rescaled
  when ``iterations`` changes (``FitConfig.scaled_to``).
"""

from __future__ import annotations

from dataclasses import asdict

from pipeline.active.config import EpisodeConfig, episode_preset

# top-level keys whose null means "the preset's value"
FROM_PRESET = ("iterations", "image_width", "max_gaussians", "epochs_per_view", "curve_test_views")
# fit fields shown elsewhere (top level) or set by the job (seed): not in the YAML's fit block
NOT_IN_FIT_BLOCK = ("iterations", "image_width", "seed", "densify.max_gaussians")


def preset_values(preset: EpisodeConfig) -> dict[str, object]:
    """The preset's value of each ``FROM_PRESET`` key."""
    return {"iterations": preset.fit.iterations, "image_width": preset.fit.image_width,
            "max_gaussians": preset.fit.densify.max_gaussians, "epochs_per_view": preset.epochs_per_view,
            "curve_test_views": preset.curve_test_views}


def fit_block(preset: EpisodeConfig) -> dict:
    """The preset's fit recipe as the YAML shows it (nested like ``FitConfig``)."""
    block = asdict(preset.fit)
    for dotted in NOT_IN_FIT_BLOCK:
        node, *rest = dotted.split(".")
        if rest:
            del block[node][rest[0]]
        else:
            del block[node]
    return block


def _changed(shown: dict, preset: dict, where: str) -> dict:
    """The entries of ``shown`` (as written) whose value differs from ``preset``'s.
    ``ValueError`` names the dotted key of an unknown one."""
    out = {}
    for key, value in shown.items():
        if key not in preset:
            raise ValueError(f"{where}{key}: unknown hyperparameter; allowed {sorted(preset)}")
        if isinstance(preset[key], dict) and isinstance(value, dict):
            inner = _changed(value, preset[key], f"{where}{key}.")
            if inner:
                out[key] = inner
        elif value != preset[key] or type(value) is bool and type(preset[key]) is not bool:
            out[key] = value
    return out


def job_form(section: dict) -> dict:
    """The composed ``splat`` section reduced to what differs from its preset (see the module).
    ``ValueError`` for an unknown preset or an unknown ``fit`` key, naming it."""
    preset = episode_preset(section["preset"])
    out = dict(section)
    for key, value in preset_values(preset).items():
        if key in out and out[key] == value and type(out[key]) is type(value):
            out[key] = None
    fit = out.pop("fit", None) or {}
    if not isinstance(fit, dict):
        raise ValueError(f"fit: a group of hyperparameters, not {fit!r}")
    changed = _changed(fit, asdict(preset.fit), "fit.")
    if changed:
        out["fit"] = changed
    return out
