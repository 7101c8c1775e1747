"""A published episode reproduces its digits in this environment (a fresh clone's `make env` from
requirements.lock): reports/reproduce/episodes.json holds the command, the picks and the final
PSNR to the last digit, and the published text quotes the same digits."""

import json
from pathlib import Path

import pytest

from tests.conftest import SHARED_DATA

ROOT = Path(__file__).resolve().parent.parent
PUBLISHED = json.loads((ROOT / "reports" / "reproduce" / "episodes.json").read_text())["episodes"]


def test_the_published_text_quotes_the_reference_digits():
    for episode in PUBLISHED:
        digits = repr(episode["final_psnr_full"])
        assert digits in (ROOT / "reports" / "speed.md").read_text()
        assert digits in (ROOT / "reports" / "paper" / "README.md").read_text()


@pytest.mark.slow
@pytest.mark.parametrize("episode", PUBLISHED, ids=[e["command"] for e in PUBLISHED])
def test_a_published_episode_reproduces_its_digits(episode, monkeypatch):
    from pipeline.bench.episode import main
    scene = Path(episode["argv"][episode["argv"].index("--scene") + 1])
    local = SHARED_DATA / scene.relative_to("../shared/data")
    if not local.is_dir():
        pytest.skip(f"{local}: the shared data is not staged here")
    argv = [str(local) if a == str(scene) else a for a in episode["argv"]]
    monkeypatch.chdir(ROOT)
    (row,) = main(argv)
    assert row["initial"] == episode["initial"]
    assert row["selected"] == episode["selected"]
    assert row["final_psnr_full"] == episode["final_psnr_full"], (
        f"{episode['command']}: {row['final_psnr_full']!r}, published {episode['final_psnr_full']!r}")
