"""Methods from outside the package: the public API's surface, discovery through a real installed
distribution's entry points and through dotted paths, each refusal, the plugin's identity in the
job hash, and the example plugin's strategy by hand."""

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import pipeline.api as api
from pipeline.acquisition.discovery import StrategyError, check_plugins, resolve_strategy
from pipeline.cli.run import CONF_DIR
from pipeline.experiment.episode_settings import ConfigError
from pipeline.experiment.build import expand_jobs
from tests.conftest import SMALL_GENERATED
from tests.api_surface import surface

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "farthest_view"
TINY = ["splat=tiny", "dataset=[generated]", *SMALL_GENERATED, "protocol.initial_views=2", "protocol.budget=3",
        "protocol.probes=3"]


def test_public_api_surface_is_unchanged():
    """A public name that disappears or changes signature fails here: bump API_VERSION (a major
    change) and regenerate tests/data/api_surface.json with tests/api_surface.py."""
    recorded = json.loads((ROOT / "tests" / "data" / "api_surface.json").read_text())
    now = surface(api)
    gone = sorted(set(recorded) - set(now))
    changed = sorted(k for k in recorded if k in now and recorded[k] != now[k])
    assert not gone and not changed, f"public API changed: gone {gone}, changed {changed}"
    assert api.API_VERSION == recorded["API_VERSION"].strip("'")


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The example plugin installed by pip (a real distribution: dist-info with entry_points.txt)."""
    target = tmp_path_factory.mktemp("site")
    source = tmp_path_factory.mktemp("src") / "farthest_view"  # pip builds in place: not in the checkout
    shutil.copytree(EXAMPLE, source, ignore=shutil.ignore_patterns("build", "*.egg-info"))
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--target", str(target), str(source)], check=True, capture_output=True)
    return target


@pytest.fixture
def on_path(installed, monkeypatch):
    monkeypatch.syspath_prepend(str(installed))
    for name in [m for m in sys.modules if m.startswith("gopre_farthest_view")]:
        monkeypatch.delitem(sys.modules, name)
    return installed


def test_installed_plugin_is_found_through_its_entry_point(on_path):
    source = resolve_strategy("farthest_view")
    assert source.cls.__name__ == "FarthestView" and source.cls.__module__ == "gopre_farthest_view"
    assert source.plugin.distribution == "gopre-farthest-view" and source.plugin.version == "0.1.0"
    assert source.plugin.reference == "farthest_view = gopre_farthest_view:FarthestView"
    assert len(source.plugin.source_sha256) == 64
    assert resolve_strategy("gopre").plugin is None  # built-ins carry no plugin identity


def test_discovery_in_a_fresh_interpreter(installed):
    """The same through PYTHONPATH in a new process, as a Ray worker or a user's shell sees it."""
    code = ("from pipeline.api import make_strategy, resolve_strategy; s = resolve_strategy('farthest_view'); "
            "print(s.plugin.distribution, type(make_strategy('farthest_view', min_angle_deg=5.0)).__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={"PYTHONPATH": f"{installed}:{ROOT}", "PATH": "/usr/bin:/bin"}, check=True)
    assert out.stdout.split() == ["gopre-farthest-view", "FarthestView"]


def composed(overrides, config_dir=None):
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides)


def plugin_jobs(tmp_path, method_yaml):
    (tmp_path / "conf" / "method").mkdir(parents=True, exist_ok=True)
    (tmp_path / "conf" / "method" / "mine.yaml").write_text(method_yaml)
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", [*TINY, "executor=local", "tracking=none", f"output_dir={tmp_path}/out",
                                 f"hydra.searchpath=[file://{tmp_path}/conf]", "method=[random,mine]"])
    return {j.method: j for j in expand_jobs(cfg)}


def test_plugin_identity_enters_the_job_hash(on_path, tmp_path):
    jobs = plugin_jobs(tmp_path, "mine:\n  strategy: farthest_view\n  options: {}\n")
    assert jobs["mine"].plugin["distribution"] == "gopre-farthest-view"
    assert "plugin" not in jobs["random"].to_dict()  # a built-in job's plain form (and hash) as before
    first = jobs["mine"].config_hash
    module = on_path / "gopre_farthest_view" / "__init__.py"
    module.write_text(module.read_text() + "\n# a changed plugin\n")
    try:
        again = plugin_jobs(tmp_path, "mine:\n  strategy: farthest_view\n  options: {}\n")
    finally:
        module.write_text(module.read_text().replace("\n# a changed plugin\n", ""))
    assert again["mine"].config_hash != first  # re-run, never "already finished"
    assert again["random"].config_hash == jobs["random"].config_hash


def fake_distribution(site: Path, name: str, entry_points: str, modules: dict[str, str] | None = None) -> None:
    """A minimal installed distribution (dist-info: METADATA and entry_points.txt), as pip leaves one."""
    info = site / f"{name}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[gopre.strategies]\n" + entry_points)
    for module, text in (modules or {}).items():
        (site / f"{module}.py").write_text(textwrap.dedent(text))


@pytest.mark.parametrize("entry, modules, message", [
    ("broken = missing_module_xyz:Strategy\n", None,
     r"^entry point gopre.strategies:broken = missing_module_xyz:Strategy \(from bad 1.0\): cannot be imported "
     r"\(ModuleNotFoundError"),
    ("noselect = nosel_mod:Thing\n", {"nosel_mod": "class Thing:\n    name = 'thing'\n"},
     r"^entry point gopre.strategies:noselect = nosel_mod:Thing \(from bad 1.0\): Thing has no select\(ctx, count\)"),
    ("afunction = fn_mod:pick\n", {"fn_mod": "def pick(ctx, count=1):\n    return None\n"},
     r"^entry point gopre.strategies:afunction = fn_mod:pick .*: is a function, not a strategy class$"),
    ("narrow = narrow_mod:Narrow\n", {"narrow_mod": "class Narrow:\n    def select(self):\n        pass\n"},
     r"Narrow.select takes \['self'\]; the protocol is select\(self, ctx, count=1\)"),
])
def test_a_plugin_that_cannot_serve_is_refused_naming_its_entry_point(tmp_path, monkeypatch, entry, modules, message):
    fake_distribution(tmp_path, "bad", entry, modules)
    monkeypatch.syspath_prepend(str(tmp_path))
    name = entry.split(" = ")[0]
    with pytest.raises(StrategyError, match=message) as err:
        resolve_strategy(name)
    assert "\n" not in str(err.value)


def test_a_plugin_reusing_a_built_in_name_refuses_the_launches_that_use_it_and_warns_the_others(
        tmp_path, monkeypatch, capsys):
    fake_distribution(tmp_path, "shadow", "gopre = shadow_mod:Fake\n",
                      {"shadow_mod": "class Fake:\n    def select(self, ctx, count=1):\n        pass\n"})
    monkeypatch.syspath_prepend(str(tmp_path))
    clash = (r"^entry point gopre.strategies:gopre = shadow_mod:Fake \(from shadow 1.0\) reuses the built-in "
             r"strategy name 'gopre'")
    with pytest.raises(StrategyError, match=clash):
        check_plugins({"random", "gopre"})
    with pytest.raises(StrategyError, match=clash):  # asked for by name: neither is a safe guess
        resolve_strategy("gopre")
    with pytest.raises(ConfigError, match="reuses the built-in strategy name 'gopre'"):
        expand_jobs(composed([*TINY, "executor=local", "tracking=none", f"output_dir={tmp_path}/o"]))
    heard = []
    check_plugins({"random"}, warn=heard.append)
    check_plugins({"random"}, warn=heard.append)  # once per process
    assert len(heard) == 1 and "reuses the built-in strategy name 'gopre'" in heard[0]
    jobs = expand_jobs(composed([*TINY, "executor=local", "tracking=none", f"output_dir={tmp_path}/o",
                                 "method=[random]"]))
    assert [j.method for j in jobs] == ["random"] and jobs[0].plugin is None


def test_a_method_key_that_is_a_built_in_name_must_run_that_strategy(tmp_path):
    """`random: {strategy: coverage}` would put another method's numbers in the row 'random'."""
    with pytest.raises(ConfigError, match=r"^method.random: the key 'random' is the built-in strategy's name, but its "
                                          r"strategy is 'coverage'; give the method another key"):
        plugin_jobs(tmp_path, "random:\n  strategy: coverage\n")


def test_dotted_paths_and_their_refusals(tmp_path, monkeypatch):
    (tmp_path / "my_scores.py").write_text(textwrap.dedent("""
        class FirstView:
            name = "first_view"
            def select(self, ctx, count=1):
                raise NotImplementedError
        NOT_A_CLASS = 3
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    source = resolve_strategy("my_scores:FirstView")
    assert source.cls.__name__ == "FirstView" and source.plugin.distribution is None
    assert source.plugin.reference == "my_scores:FirstView"
    with pytest.raises(StrategyError, match=r"^strategy 'my_scores:Missing': cannot be imported \(AttributeError"):
        resolve_strategy("my_scores:Missing")
    with pytest.raises(StrategyError, match=r"^strategy 'no_such_pkg.mod:X': cannot be imported \(ModuleNotFoundError"):
        resolve_strategy("no_such_pkg.mod:X")
    with pytest.raises(StrategyError, match=r"is a int, not a strategy class"):
        resolve_strategy("my_scores:NOT_A_CLASS")
    with pytest.raises(StrategyError, match=r"^unknown strategy 'nope'; built-in: \[.*'gopre'.*\]; installed plugins"):
        resolve_strategy("nope")


def test_a_bad_method_strategy_is_a_config_error_naming_the_method(tmp_path):
    (tmp_path / "conf" / "method").mkdir(parents=True)
    (tmp_path / "conf" / "method" / "mine.yaml").write_text("mine:\n  strategy: nowhere_pkg:Nothing\n")
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", [*TINY, "executor=local", "tracking=none", f"output_dir={tmp_path}/out",
                                 f"hydra.searchpath=[file://{tmp_path}/conf]", "method=[mine]"])
    with pytest.raises(ConfigError, match=r"^method.mine: strategy 'nowhere_pkg:Nothing': cannot be imported"):
        expand_jobs(cfg)


def test_a_preset_takes_another_method_with_one_override(tmp_path):
    """The paper presets' method list is written once (method_set/paper); +method=NAME appends."""
    (tmp_path / "method").mkdir()
    (tmp_path / "method" / "mine.yaml").write_text("mine:\n  strategy: coverage\n")
    for preset in ("table1_global", "table2_goal", "table3_sparse", "curves"):
        with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
            plain = list(compose("config", [f"experiment={preset}"]).method)
            added = list(compose("config", [f"experiment={preset}", "+method=mine",
                                            f"hydra.searchpath=[file://{tmp_path}]"]).method)
        assert plain == ["random", "coverage", "cover", "activenerf", "fisherrf", "fisherrf_nbvgym", "gaussmi",
                         "warprf", "popgs", "gopre"]
        assert added == plain + ["mine"]


# -- the example strategy, by hand --------------------------------------------------------------

def look_along(directions) -> api.Cameras:
    """Cameras at the origin whose optical axis (+z in the camera) is each direction."""
    mats = []
    for d in directions:
        z = torch.tensor(d, dtype=torch.float64)
        z = z / z.norm()
        helper = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) if abs(z[2]) < 0.9 else torch.tensor([1.0, 0, 0],
                                                                                                          dtype=torch.float64)
        x = torch.linalg.cross(helper, z)
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] = torch.stack([x, y, z])  # world -> camera rows
        mats.append(m)
    k = torch.tensor([[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]])
    return api.Cameras(torch.stack(mats).float(), k.expand(len(mats), 3, 3).clone(), 16, 16)


def test_farthest_view_by_hand(on_path):
    from gopre_farthest_view import FarthestView
    from pipeline.splat.gaussians import Gaussians
    g = Gaussians.unchecked(means=torch.zeros(1, 3), log_scales=torch.zeros(1, 3), quats=torch.tensor([[1.0, 0, 0, 0]]),
                            logit_opacities=torch.zeros(1), sh0=torch.zeros(1, 1, 3), shN=torch.zeros(1, 0, 3))
    # taken looks along +x; candidates (ids 7, 3, 5): along +x (0 deg), +y (90 deg), -x (180 deg)
    ctx = api.SelectionContext(g, look_along([[1, 0, 0], [0, 1, 0], [-1, 0, 0]]), [7, 3, 5],
                               look_along([[1, 0, 0]]), torch.zeros(3), torch.Generator().manual_seed(0))
    sel = FarthestView().select(ctx, count=2)
    assert sel.chosen == [5, 3]
    assert {k: round(v, 6) for k, v in sel.scores.items()} == {7: 0.0, 3: 90.0, 5: 180.0}
    assert FarthestView(min_angle_deg=100.0).select(ctx).scores[3] == 0.0
    with pytest.raises(ValueError, match="min_angle_deg"):
        FarthestView(min_angle_deg=180.0)


def test_model_doors_equal_the_functions_they_open():
    from pipeline.fisher.exact import view_fisher
    from pipeline.splat import render
    from pipeline.splat.gaussians import Gaussians
    gen = torch.Generator().manual_seed(0)
    n = 12
    g = Gaussians.unchecked(means=torch.randn(n, 3, generator=gen) * 0.3, log_scales=torch.full((n, 3), -2.0),
                            quats=torch.randn(n, 4, generator=gen), logit_opacities=torch.zeros(n),
                            sh0=torch.rand(n, 1, 3, generator=gen), shN=torch.zeros(n, 0, 3))
    cams = look_along([[0, 0, 1], [0, 0, 1]])
    cams.viewmats[:, 2, 3] = 3.0  # three units in front of the cameras
    cams.viewmats[1, 0, 3] = 0.2
    bg = torch.tensor([0.1, 0.2, 0.3])
    ctx = api.SelectionContext(g, cams, [0, 1], cams[[0]], bg, gen)
    doors = ctx.backend
    assert doors.name in ("compiled", "tiles")
    assert torch.equal(doors.render(cams).rgb, render(g, cams, bg).rgb)
    fisher = view_fisher(g, cams, bg)
    assert torch.equal(doors.view_fisher(cams), fisher) and fisher.abs().sum() > 0
    assert torch.allclose(doors.training_hessian(cams), fisher[0] + fisher[1], rtol=1e-12, atol=0)
    assert torch.equal(doors.training_hessian(cams[[0]][[]]), torch.zeros_like(fisher[0]))


def gopre_run(args, pythonpath, cwd):
    env = {"PYTHONPATH": pythonpath, "PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin", "HOME": str(cwd)}
    return subprocess.run([str(Path(sys.executable).parent / "gopre-run"), *args], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=300)


def test_config_dir_brings_a_method_yaml_from_outside(installed, tmp_path):
    """`gopre-run --config-dir DIR ... +method=NAME`, as the README says, before any job starts."""
    args = ["--config-dir", str(EXAMPLE / "conf"), "experiment=table2_goal", "+method=farthest_view",
            "dataset=[generated]", "splat=tiny", "plan=true", f"output_dir={tmp_path}/out"]
    done = gopre_run(args, str(installed), tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("farthest_view") >= 1 and "gopre" in done.stdout
    missing = gopre_run(args, "", tmp_path)  # the plugin not installed: one line, exit 2, nothing started
    assert missing.returncode == 2
    last = missing.stderr.strip().splitlines()[-1]
    assert last.startswith("gopre-run: config error: method.farthest_view: unknown strategy 'farthest_view'")
    assert not (tmp_path / "out" / "jobs").exists()
