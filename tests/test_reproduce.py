"""A published episode reproduces its digits in this environment (a fresh clone's `make env` from
requirements.lock): reports/reproduce/episodes.json holds the command, the picks and the final
PSNR to the last digit, and the published text quotes the same digits."""

import json
from pathlib import Path

import pytest

from tests.conftest import SHARED_DATA

ROOT = Path(__file__).resolve().parent.parent
PUBLISHED = json.loads((ROOT / "reports" / "reproduce" / "episodes.json").read_text())["episodes"]


QUOTED_BY_DEFAULT = ("reports/speed.md", "reports/paper/README.md")


def test_the_published_text_quotes_the_reference_digits():
    for episode in PUBLISHED:
        digits = repr(episode["final_psnr_full"])
        for page in episode.get("quoted_in", QUOTED_BY_DEFAULT):
            assert digits in (ROOT / page).read_text(), f"{page} does not quote {episode['command']}'s {digits}"


def reproduce_all() -> bool:
    """`make reproduce` (CI runs it after `make test`): every published digit, the long episodes too."""
    import os
    return os.environ.get("GOPRE_REPRODUCE_ALL") == "1"


@pytest.mark.slow
@pytest.mark.parametrize("episode", PUBLISHED, ids=[e["command"] for e in PUBLISHED])
def test_a_published_episode_reproduces_its_digits(episode, monkeypatch):
    if not episode.get("suite", True) and not reproduce_all():
        pytest.skip(f"not in the suite ({episode['why_not_in_the_suite']})")
    from pipeline.bench.episode import main
    scene = Path(episode["argv"][episode["argv"].index("--scene") + 1])
    local = SHARED_DATA / scene.relative_to("../shared/data")
    if not local.is_dir():
        pytest.skip(f"{local}: the shared data is not staged here")
    argv = [str(local) if a == str(scene) else a for a in episode["argv"]]
    monkeypatch.chdir(ROOT)
    (row,) = main(argv)
    where = (f"published under {episode['numerics']!r}, run here under {row['numerics']!r} "
             "(reports/reproduce/README.md: which code paths move the digits)")
    assert row["initial"] == episode["initial"]
    assert row["selected"] == episode["selected"], where
    assert row["final_psnr_full"] == episode["final_psnr_full"], (
        f"{episode['command']}: {row['final_psnr_full']!r}, published {episode['final_psnr_full']!r}; {where}")


def readme_demo_table() -> dict[str, float]:
    """The README's demo table: method -> generated PSNR as printed (two decimals)."""
    lines = (ROOT / "README.md").read_text().splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith("| Method | generated PSNR |"))
    rows = {}
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip().strip("*_").replace("<ins>", "").replace("</ins>", "") for c in line.strip("|").split("|")]
        rows[cells[0]] = float(cells[1])
    return rows


@pytest.mark.slow
def test_the_demo_gives_the_readme_table(tmp_path):
    """`make demo` on a fresh clone prints the README's table: the demo sweep (run here without Ray
    or MLflow, which give the same numbers) ends each method at the README's PSNR. Four episodes,
    142 CPU s: `make reproduce` runs it (CI too, after `make test`); the suite checks digits with the
    tiny published episodes."""
    if not reproduce_all():
        pytest.skip("not in the suite (142 CPU s): `make reproduce` runs it, and CI after `make test`")
    from hydra import compose, initialize_config_dir

    from pipeline.cli.run import CONF_DIR
    from pipeline.experiment.records import RecordsFile
    from pipeline.experiment.sweep import run_sweep
    with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", ["experiment=demo", "executor=local", "tracking=none", "job.round_models=false",
                                 f"output_dir={tmp_path / 'demo'}"])
    run_sweep(cfg)
    finals = RecordsFile(tmp_path / "demo").frame
    finals = finals[finals["kind"] == "final"]
    got = {m: round(float(p), 2) for m, p in zip(finals["method"], finals["psnr"])}
    assert got == readme_demo_table()
