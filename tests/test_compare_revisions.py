"""tools/compare_revisions.py pairs old and new runs by (method, scene, seed, setting)."""

import importlib.util
from pathlib import Path

import pandas as pd

spec = importlib.util.spec_from_file_location(
    "compare_revisions", Path(__file__).resolve().parents[1] / "tools" / "compare_revisions.py")
compare = importlib.util.module_from_spec(spec)
spec.loader.exec_module(compare)


def rows(values):
    return pd.DataFrame([{"scene": s, "setting": "g", "method": m, "seed": k, "psnr": v, "status": st}
                         for s, m, k, v, st in values])


def test_pairs_only_runs_finished_in_both_and_differences_are_new_minus_old(tmp_path, capsys):
    old = rows([("lego", "gopre", 0, 20.0, "FINISHED"), ("lego", "gopre", 1, 21.0, "FINISHED"),
                ("lego", "gopre", 2, 99.0, "FAILED"), ("lego", "random", 0, 18.0, "FINISHED")])
    new = rows([("lego", "gopre", 0, 21.5, "FINISHED"), ("lego", "gopre", 1, 20.5, "FINISHED"),
                ("lego", "gopre", 2, 22.0, "FINISHED"), ("lego", "coverage", 0, 19.0, "FINISHED")])
    old.to_csv(tmp_path / "old.csv", index=False)
    new.to_csv(tmp_path / "new.csv", index=False)
    assert compare.main([str(tmp_path / "old.csv"), str(tmp_path / "new.csv")]) == 0
    out = capsys.readouterr().out
    assert "| lego | g | gopre | 2 | 20.50 | 21.00 | +0.50 (-0.50, +1.50) |" in out
    assert "random" in out.split("old file only: ")[1] and "coverage" in out.split("new file only: ")[1]
