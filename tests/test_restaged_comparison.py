"""tools/restaged_comparison.py: old beside new per method, of one scene and one setting."""

import importlib.util
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("restaged_comparison", ROOT / "tools" / "restaged_comparison.py")
tool = importlib.util.module_from_spec(spec)
sys.modules["restaged_comparison"] = tool
spec.loader.exec_module(tool)


def runs(rows):
    return pd.DataFrame([{"method": m, "scene": sc, "seed": seed, "setting": st, "status": "FINISHED", "psnr": p}
                         for m, sc, seed, st, p in rows])


def test_one_setting_of_one_scene_old_beside_new(tmp_path, capsys):
    old = runs([("gopre", "bonsai", 0, "protocol.kind=goal", 20.0), ("gopre", "bonsai", 1, "protocol.kind=goal", 22.0),
                ("gopre", "bonsai", 0, "protocol.kind=global", 99.0), ("gopre", "lego", 0, "protocol.kind=goal", 99.0),
                ("random", "bonsai", 0, "protocol.kind=goal", 18.0)])
    new = runs([("gopre", "bonsai", 0, "protocol.kind=goal", 24.0), ("gopre", "bonsai", 1, "protocol.kind=goal", 25.0),
                ("gopre", "bonsai", 0, "protocol.kind=global", -99.0)])
    old.to_csv(tmp_path / "old.csv", index=False)
    new.to_csv(tmp_path / "new.csv", index=False)
    assert tool.main([str(tmp_path / "old.csv"), str(tmp_path / "new.csv"), "--scene", "bonsai",
                      "--setting", "protocol.kind=goal"]) == 0
    out = capsys.readouterr().out
    assert "| gopre | 21.00 ± 1.41 (2) | 24.50 ± 0.71 (2) | +3.50 |" in out  # the other setting and scene left out
    assert "| random | 18.00 (1) | n/a | n/a |" in out


def test_two_settings_without_a_choice_are_refused(tmp_path):
    both = runs([("gopre", "bonsai", 0, "protocol.kind=goal", 20.0), ("gopre", "bonsai", 0, "protocol.kind=global", 21.0)])
    both.to_csv(tmp_path / "both.csv", index=False)
    with pytest.raises(SystemExit, match="runs of 2 settings .*name one with --setting"):
        tool.main([str(tmp_path / "both.csv"), str(tmp_path / "both.csv"), "--scene", "bonsai"])
