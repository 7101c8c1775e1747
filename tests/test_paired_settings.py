"""tools/paired_settings.py pairs two settings' episodes seed by seed on the same data and refuses two
data fingerprints."""

import importlib.util
import sys
from pathlib import Path

import pandas as pd

spec = importlib.util.spec_from_file_location(
    "paired_settings", Path(__file__).resolve().parents[1] / "tools" / "paired_settings.py")
paired = importlib.util.module_from_spec(spec)
sys.modules["paired_settings"] = paired
spec.loader.exec_module(paired)


def _runs(path, rows, fingerprint="f" * 16):
    pd.DataFrame([{"method": m, "scene": "s", "seed": k, "psnr": v, "status": st, "data_fingerprint": fingerprint}
                  for m, k, v, st in rows]).to_csv(path, index=False)
    return path


def test_differences_are_other_minus_baseline_over_the_seeds_both_finished(tmp_path, capsys):
    base = _runs(tmp_path / "a.csv", [("gopre", 0, 20.0, "FINISHED"), ("gopre", 1, 21.0, "FINISHED"),
                                      ("gopre", 2, 30.0, "FAILED"), ("random", 0, 18.0, "FINISHED")])
    other = _runs(tmp_path / "b.csv", [("gopre", 0, 21.0, "FINISHED"), ("gopre", 1, 21.5, "FINISHED"),
                                       ("gopre", 2, 10.0, "FINISHED"), ("random", 0, 17.0, "FINISHED")])
    assert paired.main([str(base), str(other), "--scene", "s"]) == 0
    out = capsys.readouterr().out
    assert "| gopre | 20.50 | 21.25 | +0.75 [" in out and "(n = 2) | 2 / 0 / 0 |" in out  # seed 2 failed at baseline
    assert "| random | 18.00 | 17.00 | -1.00 [-1.00, -1.00] (n = 1) | 0 / 1 / 0 |" in out


def test_two_data_fingerprints_are_refused_naming_both(tmp_path, capsys):
    base = _runs(tmp_path / "a.csv", [("gopre", 0, 20.0, "FINISHED")], fingerprint="a" * 16)
    other = _runs(tmp_path / "b.csv", [("gopre", 0, 21.0, "FINISHED")], fingerprint="b" * 16)
    assert paired.main([str(base), str(other), "--scene", "s"]) == 2
    out = capsys.readouterr().out
    assert "not the same data" in out and "a" * 16 in out and "b" * 16 in out and "|" not in out
