"""``result.json`` and benchmark definitions: validation against their JSON Schemas (files beside
this module), the protocol check that matches a result with the benchmark it claims, and the
result as the records' rows the reports read.

A result is *accepted* for (dataset, scene, protocol, seed, setting) when its ``views`` block equals
the definition's in every field of ``CHECKED_VIEW_FIELDS`` (splits, initial views, pool, test
views, budget, the sha256 of every ground-truth test image); the first differing field is named.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

RESULT_SCHEMA = "gopre.result"
BENCHMARK_SCHEMA = "gopre.benchmark"
SCHEMA_VERSION = 1
HERE = Path(__file__).resolve().parent
CHECKED_VIEW_FIELDS = ("pool_split", "test_split", "initial_ids", "pool_ids", "test_ids", "budget",
                       "test_image_sha256")


class DocumentError(ValueError):
    """A result or benchmark file that is malformed or does not match; one line naming the file
    and the field."""


@lru_cache(maxsize=None)
def schema(name: str) -> dict:
    """The JSON Schema ``result`` or ``benchmark`` (``<name>.schema.json`` in this package)."""
    return json.loads((HERE / f"{name}.schema.json").read_text())


@lru_cache(maxsize=None)
def _validator(name: str):
    import jsonschema
    from referencing import Registry, Resource
    registry = Registry().with_resources(
        (f"{n}.schema.json", Resource.from_contents(schema(n))) for n in ("result", "benchmark"))
    cls = jsonschema.validators.validator_for(schema(name))
    return cls(schema(name), registry=registry)


def validate(doc: dict, name: str, source: str) -> dict:
    """``doc`` checked against schema ``name``; DocumentError names ``source`` and the JSON path."""
    errors = sorted(_validator(name).iter_errors(doc), key=lambda e: list(e.absolute_path))
    if errors:
        err = errors[0]
        where = "/".join(str(p) for p in err.absolute_path) or "(top level)"
        raise DocumentError(f"{source}: not a valid {name} file (schema version {SCHEMA_VERSION}): "
                            f"{where}: {err.message}")
    return doc


def read(path: str | Path, name: str) -> dict:
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise DocumentError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DocumentError(f"{path}: cannot read it as JSON ({err})") from None
    if not isinstance(doc, dict):
        raise DocumentError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    expected = RESULT_SCHEMA if name == "result" else BENCHMARK_SCHEMA
    if doc.get("schema") == expected and doc.get("schema_version") != SCHEMA_VERSION:
        raise DocumentError(f"{path}: schema_version {doc.get('schema_version')!r}; this gopre reads "
                            f"version {SCHEMA_VERSION}")
    return validate(doc, name, str(path))


def key_of(benchmark: dict) -> tuple:
    """(dataset, scene, protocol, seed, setting) of a result's or an entry's ``benchmark`` block."""
    return (benchmark["dataset"], benchmark["scene"], benchmark["protocol"], int(benchmark["seed"]),
            benchmark.get("setting") or "")


def describe(key: tuple) -> str:
    dataset, scene, protocol, seed, setting = key
    return f"{dataset}/{scene} {protocol} seed {seed}" + (f" ({setting})" if setting else "")


def check_views(result: dict, definition_views: dict, source: str, against: str) -> None:
    """Refuse a result whose views differ from the definition's, naming the first field."""
    views = result["views"]
    mine, theirs = views.get("data_fingerprint"), definition_views.get("data_fingerprint")
    if mine and theirs and mine != theirs:
        raise DocumentError(f"{source}: views.data_fingerprint is {mine}, {against} has {theirs}: computed on "
                            "other data (the scene's files changed)")
    for name in CHECKED_VIEW_FIELDS:
        mine, theirs = views.get(name), definition_views.get(name)
        if name == "test_image_sha256":
            mine, theirs = {str(k): v for k, v in (mine or {}).items()}, {str(k): v for k, v in (theirs or {}).items()}
            differ = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
            if differ:
                raise DocumentError(f"{source}: views.test_image_sha256 differs from {against} for test "
                                    f"view(s) {differ[:5]}{' ...' if len(differ) > 5 else ''}: not the same "
                                    "ground-truth images")
        elif mine != theirs:
            raise DocumentError(f"{source}: views.{name} is {_short(mine)}, {against} has {_short(theirs)}")
    mine, theirs = views.get("image_width"), definition_views.get("image_width")
    if mine is not None and theirs is not None and int(mine) != int(theirs):
        raise DocumentError(f"{source}: views.image_width is {mine}, {against} has {theirs}: scored at another "
                            "resolution")
    taken = list(views["initial_ids"]) + [i for r in result["rounds"] for i in r["selected"]]
    allowed = set(views["initial_ids"]) | set(views["pool_ids"])
    outside = [i for i in taken if i not in allowed]
    if outside:
        raise DocumentError(f"{source}: rounds select view(s) {outside[:5]} outside the benchmark's pool")
    if len(taken) > int(views["budget"]):
        raise DocumentError(f"{source}: {len(taken)} views taken, over the benchmark's budget of {views['budget']}")
    tested = sorted(int(p["test_id"]) for p in result["final"]["per_image"])
    if tested != sorted(views["test_ids"]):
        raise DocumentError(f"{source}: final.per_image covers test views {_short(tested)}, the benchmark's are "
                            f"{_short(sorted(views['test_ids']))}")


# how far a result's headline may be from the mean of its per-image values (rounding, float32 sums)
PSNR_TOLERANCE_DB = 0.01
SSIM_TOLERANCE = 0.001


def check_claims(result: dict, source: str) -> None:
    """A result agrees with itself, whatever benchmark it names: ``final.psnr`` (and ``ssim``) is the
    mean of ``final.per_image`` to ``PSNR_TOLERANCE_DB`` (``SSIM_TOLERANCE``), as gopre's own results
    are; the rounds count the views they train on (the first round the initial views, each next one
    the previous plus its picks, ``final.num_views`` all of them); no view is taken twice (a pick of an
    initial view, of an earlier pick, or twice in one round). DocumentError names file and field."""
    final, per_image = result["final"], result["final"]["per_image"]
    psnr = sum(float(p["psnr"]) for p in per_image) / len(per_image)
    if abs(float(final["psnr"]) - psnr) > PSNR_TOLERANCE_DB:
        raise DocumentError(f"{source}: final.psnr is {final['psnr']}, the mean of final.per_image's psnr is "
                            f"{psnr:.4f} (tolerance {PSNR_TOLERANCE_DB} dB)")
    ssims = [p.get("ssim") for p in per_image]
    if final.get("ssim") is not None and all(v is not None for v in ssims):
        ssim = sum(float(v) for v in ssims) / len(ssims)
        if abs(float(final["ssim"]) - ssim) > SSIM_TOLERANCE:
            raise DocumentError(f"{source}: final.ssim is {final['ssim']}, the mean of final.per_image's ssim is "
                                f"{ssim:.4f} (tolerance {SSIM_TOLERANCE})")
    tested = [int(p["test_id"]) for p in per_image]
    if len(set(tested)) != len(tested):
        raise DocumentError(f"{source}: final.per_image lists test view(s) "
                            f"{sorted({t for t in tested if tested.count(t) > 1})} more than once")
    seen, count = list(result["views"]["initial_ids"]), len(result["views"]["initial_ids"])
    for k, r in enumerate(result["rounds"]):
        if int(r["num_views"]) != count:
            raise DocumentError(f"{source}: rounds[{k}].num_views is {r['num_views']}, but {count} views were "
                                "taken by then (the initial views and the picks of the rounds before)")
        again = sorted({i for i in r["selected"] if i in seen or r["selected"].count(i) > 1})
        if again:
            raise DocumentError(f"{source}: rounds[{k}].selected takes view(s) {again} already taken or twice")
        seen += list(r["selected"])
        count += len(r["selected"])
    if int(final["num_views"]) != count:
        raise DocumentError(f"{source}: final.num_views is {final['num_views']}, the rounds took {count} views")


def _short(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 80 else text[:77] + "..."


def result_rows(doc: dict, source: str, index: int) -> list[dict]:
    """A result as records rows (``round`` rows and one ``final`` row), as a sweep's would be."""
    b, method = doc["benchmark"], doc["method"]
    plugin = method.get("plugin") or {}
    base = {"sweep": f"results:{Path(source).parent.name or source}", "job_index": index,
            "config_hash": doc.get("config_hash") or f"result:{source}", "run_id": None, "status": "FINISHED",
            "job_kind": "episode", "dataset": b["dataset"], "scene": b["scene"], "method": method["name"],
            "strategy": method.get("strategy") or method["name"], "protocol": b["protocol"],
            "seed": int(b["seed"]), "setting": b.get("setting") or "", "axes": "{}",
            "code_version": doc["code_version"], "data_fingerprint": doc["views"].get("data_fingerprint"),
            "world": "dataset", "result_file": str(source),
            **({"plugin": plugin.get("reference"), "plugin_distribution": plugin.get("distribution"),
                "plugin_version": plugin.get("version"), "plugin_sha256": plugin.get("source_sha256")}
               if plugin else {})}
    rows = [{**base, "kind": "round", "num_views": r["num_views"], "psnr": r.get("psnr"), "ssim": r.get("ssim"),
             "selection_seconds": r.get("selection_seconds"),
             "selection_cpu_seconds": r.get("selection_cpu_seconds"), "selected": json.dumps(r["selected"])}
            for r in doc["rounds"]]
    picks = [r for r in doc["rounds"] if r["selected"]]
    final = doc["final"]
    rows.append({**base, "kind": "final", "num_views": final["num_views"], "psnr": final["psnr"],
                 "ssim": final.get("ssim"), "lpips": final.get("lpips"), "metrics_version": 2,
                 "lpips_status": "from result.json" if final.get("lpips") is not None else "not in result.json",
                 "test_views": len(final["per_image"]), "degraded": False,
                 "selection_seconds": _mean([r.get("selection_seconds") for r in picks]),
                 "selection_cpu_seconds": _mean([r.get("selection_cpu_seconds") for r in picks]),
                 "initial": json.dumps(doc["views"]["initial_ids"]),
                 "selected": json.dumps([i for r in doc["rounds"] for i in r["selected"]])})
    return rows


def _mean(values: list) -> float | None:
    present = [float(v) for v in values if v is not None]
    return sum(present) / len(present) if present else None
