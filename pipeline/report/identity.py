"""What each row of a report is: the code, the plugin and the data behind it, one of each.

A table row is a method (under one setting); its cells average episodes over seeds (and over the
scenes of a dataset). Those episodes must be the same method on the same data: one code version and
one plugin identity per row, one data fingerprint per (row, dataset, scene, protocol). Otherwise the
row would be the mean of different things (three versions of a plugin run into one folder, a scene
whose files changed between launches), and the report refuses it with one line naming the two
identities, unless ``--allow-mixed`` asks for it (the report then lists every identity per row).

A record without a column (written before it existed) counts as "not recorded", which is an
identity of its own: a row mixing it with a recorded value is mixed too.
"""

from __future__ import annotations

import pandas as pd

from pipeline.report.rows import finished

NOT_RECORDED = "not recorded"
# (column, what it names, the row key beyond method and setting it must be unique within)
RULES = (("code_version", "code version", ()),
         ("plugin_identity", "plugin", ()),
         ("data_fingerprint", "data fingerprint", ("dataset", "scene", "protocol")))


class MixedRowError(ValueError):
    """A report row that would average unlike episodes; one line naming both identities."""


def _with_identities(final: pd.DataFrame) -> pd.DataFrame:
    """The final rows with one text column per identity ('not recorded' where missing)."""
    out = final.copy()
    if "setting" not in out:
        out["setting"] = ""
    out["setting"] = out["setting"].fillna("")
    plugin = pd.Series(["built-in"] * len(out), index=out.index)  # records hold plugin columns only for plugins
    if "plugin_sha256" in out:
        versions = out["plugin_version"] if "plugin_version" in out else pd.Series(None, index=out.index)
        plugin = pd.Series([f"{v or 'no version'} (source sha256 {s[:12]})" if isinstance(s, str) else "built-in"
                            for s, v in zip(out["plugin_sha256"], versions)], index=out.index)
    out["plugin_identity"] = plugin
    for column in ("code_version", "data_fingerprint"):
        values = out[column] if column in out else pd.Series(None, index=out.index)
        out[column] = [v if isinstance(v, str) and v else NOT_RECORDED for v in values]
    return out


def _row_label(method: str, setting: str) -> str:
    return f"{method} ({setting})" if setting else method


def mixed_rows(frame: pd.DataFrame) -> list[str]:
    """One line per (row, identity) that holds more than one value."""
    final = finished(frame, "final", "episode") if "job_kind" in frame else frame[frame["kind"] == "final"]
    if final.empty:
        return []
    final = _with_identities(final)
    problems = []
    for column, what, extra in RULES:
        keys = ["method", "setting", *[k for k in extra if k in final]]
        for key, part in final.groupby(keys, sort=False, dropna=False):
            values = list(dict.fromkeys(part[column]))
            if len(values) < 2:
                continue
            key = key if isinstance(key, tuple) else (key,)
            where = "" if len(key) == 2 else " on " + "/".join(str(k) for k in key[2:4])
            counts = part[column].value_counts()
            problems.append(f"row {_row_label(key[0], key[1])!r}{where} mixes {what}s {values[0]} "
                            f"({counts[values[0]]} episode(s)) and {values[1]} ({counts[values[1]]})"
                            + (f" and {len(values) - 2} more" if len(values) > 2 else ""))
    return problems


def check_rows(frame: pd.DataFrame, allow_mixed: bool = False) -> None:
    """Refuse a report whose rows mix identities (``mixed_rows``), unless ``allow_mixed``."""
    problems = mixed_rows(frame)
    if problems and not allow_mixed:
        more = f" ({len(problems) - 1} more such row(s))" if len(problems) > 1 else ""
        raise MixedRowError(f"{problems[0]}{more}: a row must average one method on one data; report them "
                            "separately, or pass --allow-mixed to report the mean anyway (each row's "
                            "identities are then listed)")


def identity_markdown(frame: pd.DataFrame) -> str:
    """The report's header section: per row, the code versions, plugin and data fingerprints it averages."""
    final = finished(frame, "final", "episode") if "job_kind" in frame else frame[frame["kind"] == "final"]
    if final.empty:
        return ""
    final = _with_identities(final)
    lines = ["## What each row averages", "",
             "| row | episodes | code version | plugin | data fingerprint per scene |", "|---|---|---|---|---|"]
    for (method, setting), part in final.groupby(["method", "setting"], sort=False):
        data = "; ".join(f"{scene}: {', '.join(dict.fromkeys(p['data_fingerprint']))}"
                         for scene, p in part.groupby("scene", sort=False))
        lines.append(f"| {_row_label(method, setting)} | {len(part)} | "
                     f"{', '.join(dict.fromkeys(part['code_version']))} | "
                     f"{', '.join(dict.fromkeys(part['plugin_identity']))} | {data} |")
    mixed = mixed_rows(frame)
    if mixed:
        lines += ["", "**Mixed rows, reported with `--allow-mixed`:** " + "; ".join(mixed) + "."]
    return "\n".join(lines) + "\n"
