"""Results from anywhere in a sweep's tables: ``gopre-report SWEEP --results DIR_OR_GLOB``.

Each ``result.json`` (``pipeline.interchange``'s schema; a directory is searched for them) is
validated, matched with the benchmark it claims, (dataset, scene, protocol, seed, setting), and
refused naming the file and the first differing field unless its views equal the reference's:
a definition from ``--benchmark FILE`` (``gopre-data benchmark``), else the same benchmark's
``result.json`` written by a job of the reported sweeps. Accepted results become records rows
beside the sweep's (same tables, same paired comparisons). A result that ships its renders
(``renders/<test_id>.png`` beside it) is scored from them against the ground truth as the episodes
read it (``rescore``, given by the command: ``pipeline.eval.outside_renders``); its rows say which
(``metrics_source``).
"""

from __future__ import annotations

import glob
import json
from pathlib import Path

import pandas as pd

from pipeline.interchange.documents import (RESULT_SCHEMA, DocumentError, check_claims, check_views, describe,
                                            key_of, read, result_rows)
from pipeline.interchange.layout import SweepFolder


def result_files(patterns: list[str]) -> list[Path]:
    """Every result.json a pattern names: a file, a directory (searched recursively for files of
    the result schema) or a glob; a pattern that names nothing is an error."""
    found: list[Path] = []
    for pattern in patterns:
        path = Path(pattern)
        if path.is_dir():
            hits = [p for p in sorted(path.rglob("*.json")) if _is_result(p)]
        elif path.is_file():
            hits = [path]
        else:
            hits = [Path(p) for p in sorted(glob.glob(pattern, recursive=True)) if Path(p).is_file()]
        if not hits:
            raise DocumentError(f"--results {pattern}: no result.json there")
        found += [p for p in hits if p not in found]
    return found


def _is_result(path: Path) -> bool:
    try:
        return json.loads(path.read_text()).get("schema") == RESULT_SCHEMA
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
        return False


def references(benchmarks: list[str], sweeps: list[Path]) -> dict[tuple, tuple[dict, str]]:
    """Benchmark key -> (views, where it came from): the --benchmark files' entries first, then
    the reported sweeps' own result.json files."""
    out: dict[tuple, tuple[dict, str]] = {}
    for file in benchmarks:
        doc = read(file, "benchmark")
        for entry in doc["entries"]:
            out.setdefault(key_of(entry["benchmark"]), (entry["views"], f"the benchmark definition {file}"))
    for sweep in sweeps:
        folder = SweepFolder(sweep if sweep.is_dir() else sweep.parent)
        for path in folder.benchmark_results():
            doc = read(path, "result")
            out.setdefault(key_of(doc["benchmark"]), (doc["views"], f"sweep {folder.path} (job {doc.get('config_hash')})"))
    return out


def method_identities(frame: pd.DataFrame | None) -> dict[str, set[tuple]]:
    """The reported sweeps' methods and the identities their rows carry: (strategy, code version,
    plugin source sha256 or None)."""
    if frame is None or frame.empty:
        return {}
    final = frame[frame["kind"] == "final"]
    plugins = final["plugin_sha256"] if "plugin_sha256" in final else pd.Series(None, index=final.index)
    codes = final["code_version"] if "code_version" in final else pd.Series(None, index=final.index)
    out: dict[str, set[tuple]] = {}
    for method, strategy, code, plugin in zip(final["method"], final["strategy"], codes, plugins):
        out.setdefault(method, set()).add((strategy, code if isinstance(code, str) else None,
                                           plugin if isinstance(plugin, str) else None))
    return out


def result_identity(doc: dict) -> tuple:
    method = doc["method"]
    return (method.get("strategy") or method["name"], doc["code_version"],
            (method.get("plugin") or {}).get("source_sha256"))


def check_name(doc: dict, source: str, methods: dict[str, set[tuple]]) -> None:
    """A result named like one of the sweep's methods must be that method (same strategy, code and
    plugin): else its numbers would be averaged into that method's row."""
    name = doc["method"]["name"]
    if name in methods and result_identity(doc) not in methods[name]:
        strategy, code, plugin = result_identity(doc)
        theirs = sorted(methods[name], key=str)[0]
        raise DocumentError(f"{source}: method.name {name!r} is a method of the reported sweep, but this result is "
                            f"another identity (strategy {strategy!r}, code {code!r}"
                            + (f", plugin {plugin[:12]}" if plugin else "")
                            + f"; the sweep's: strategy {theirs[0]!r}, code {theirs[1]!r}): give it its own name")


def rescored(doc: dict, metrics) -> dict:
    """``doc`` with its per-image and final PSNR / SSIM replaced by ``metrics`` (recomputed from its
    shipped renders: ``pipeline.eval.outside_renders``)."""
    per_image = [{**item, "psnr": float(p), "ssim": float(s)}
                 for item, p, s in zip(doc["final"]["per_image"], metrics.psnr, metrics.ssim)]
    final = {**doc["final"], "per_image": per_image, "psnr": sum(metrics.psnr) / len(metrics.psnr),
             "ssim": sum(metrics.ssim) / len(metrics.ssim)}
    return {**doc, "final": final}


def external_rows(patterns: list[str], benchmarks: list[str], sweeps: list[Path],
                  known_hashes: set[str], first_index: int = 0,
                  methods: dict[str, set[tuple]] | None = None, rescore=None) -> pd.DataFrame:
    """The accepted results as records rows; results already in the sweep (same config hash)
    are left out. Each is checked against itself (``check_claims``), against the sweep's method
    names (``check_name``: ``methods`` from ``method_identities``) and against the benchmark's views;
    DocumentError names the file and field of the first refused result."""
    refs = references(benchmarks, sweeps)
    rows = []
    for k, path in enumerate(result_files(patterns)):
        doc = read(path, "result")
        if doc.get("config_hash") in known_hashes:
            continue
        key = key_of(doc["benchmark"])
        if key not in refs:
            raise DocumentError(f"{path}: no benchmark definition for {describe(key)}: pass --benchmark FILE "
                                "(gopre-data benchmark PRESET --out FILE) or the sweep that ran it")
        views, where = refs[key]
        check_views(doc, views, str(path), where)
        check_claims(doc, str(path))
        check_name(doc, str(path), methods or {})
        metrics = rescore(doc, path) if rescore is not None else None  # None: no renders shipped
        source = "as the file states"
        if metrics is not None:
            doc = rescored(doc, metrics)
            source = (f"recomputed from its {len(metrics.psnr)} renders (the file's own PSNR up to "
                      f"{metrics.largest_psnr_gap_db:.3f} dB away)")
        rows += [{**row, "metrics_source": source} for row in result_rows(doc, str(path), first_index + k)]
    return pd.DataFrame(rows)
