"""Reports from a fixture set of records: marks, mean +- std, missing cells, LaTeX, figures."""

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.report.report import make_report
from pipeline.report.tables import build_table, to_latex, to_markdown


def final_row(method, dataset, scene, seed, psnr, ssim, lpips=None, setting="", **extra):
    return {"sweep": "fixture", "config_hash": f"{method}-{dataset}-{scene}-{seed}-{setting}",
            "run_id": None, "status": "FINISHED", "job_kind": "episode", "kind": "final", "dataset": dataset,
            "scene": scene, "method": method, "strategy": method, "protocol": "global", "seed": seed,
            "setting": setting, "axes": "{}", "psnr": psnr, "ssim": ssim, "lpips": lpips,
            "lpips_status": "vgg" if lpips is not None else "LPIPS (vgg) unavailable: no weights", **extra}


@pytest.fixture
def records():
    rows = []
    # blender: two scenes, two seeds; psnr of (method, seed) = mean over the two scenes
    values = {"gopre": [(25.0, 27.0), (26.0, 28.0)], "fisherrf": [(24.0, 26.0), (25.0, 25.0)],
              "random": [(20.0, 22.0), (21.0, 21.0)], "coverage": [(23.0, 23.0), (23.0, 23.0)]}
    for method, seeds in values.items():
        for seed, (a, b) in enumerate(seeds):
            rows.append(final_row(method, "blender", "lego", seed, a, 0.9, None))
            rows.append(final_row(method, "blender", "chair", seed, b, 0.8, None))
    # mipnerf360 run for two methods only, one seed, with LPIPS
    rows.append(final_row("gopre", "mipnerf360", "bonsai", 0, 21.0, 0.6, 0.30))
    rows.append(final_row("random", "mipnerf360", "bonsai", 0, 19.0, 0.5, 0.40))
    for method in ("gopre", "random"):
        for n, p in ((2, 12.0), (3, 15.0), (4, 18.0)):
            rows.append({**final_row(method, "blender", "lego", 0, p + (method == "gopre"), 0.5),
                         "kind": "round", "num_views": n})
    failed = final_row("popgs", "blender", "lego", 0, None, None)
    rows.append({**failed, "status": "FAILED", "error": "Traceback ..."})
    return pd.DataFrame(rows)


def test_mean_std_over_seeds_and_ranks(records):
    final = records[(records["kind"] == "final") & (records["status"] == "FINISHED")]
    table = build_table(final, "t", "method", "dataset", ["psnr", "ssim", "lpips"])
    gopre = table.cells[("gopre", ("blender", "psnr"))]
    per_seed = [26.0, 27.0]  # mean over lego/chair for seeds 0 and 1
    assert gopre.mean == pytest.approx(np.mean(per_seed)) and gopre.std == pytest.approx(np.std(per_seed, ddof=1))
    ranks = {m: table.cells[(m, ("blender", "psnr"))].rank for m in ("gopre", "fisherrf", "coverage", "random")}
    assert ranks == {"gopre": 1, "fisherrf": 2, "coverage": 3, "random": None}
    # LPIPS: lower is better; one seed -> no std
    assert table.cells[("gopre", ("mipnerf360", "lpips"))].rank == 1
    assert table.cells[("random", ("mipnerf360", "lpips"))].rank == 2
    assert table.cells[("gopre", ("mipnerf360", "lpips"))].std is None


def test_markdown_marks_and_missing_cells(records):
    final = records[(records["kind"] == "final") & (records["status"] == "FINISHED")]
    md = to_markdown(build_table(final, "Table 1", "method", "dataset", ["psnr", "ssim", "lpips"]))
    row = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
           for line in md.splitlines() if line.startswith("| ") and not line.startswith("| method")}
    assert row["gopre"][0] == "**26.50 ± 0.71**"
    assert row["fisherrf"][0] == "<ins>25.00 ± 0.00</ins>"  # second: underlined, as \second
    assert row["coverage"][0] == "_23.00 ± 0.00_"
    assert row["random"][0] == "21.00 ± 0.00"
    assert row["fisherrf"][3] == "n/a" and row["coverage"][5] == "n/a"  # mipnerf360 not run
    assert row["gopre"][2] == "n/a"  # blender LPIPS unavailable, not zero
    assert "0.000" not in row["gopre"][2]


def test_latex_is_balanced_booktabs_with_macros(records):
    final = records[(records["kind"] == "final") & (records["status"] == "FINISHED")]
    tex = to_latex(build_table(final, "Global_results & more", "method", "dataset", ["psnr", "ssim", "lpips"]))
    for env in ("table", "tabular"):
        assert tex.count(rf"\begin{{{env}}}") == tex.count(rf"\end{{{env}}}") == 1
    assert tex.count("{") == tex.count("}")
    assert r"\toprule" in tex and r"\midrule" in tex and r"\bottomrule" in tex
    assert r"\best{26.50 \pm 0.71}" in tex and r"\second{" in tex and r"\third{" in tex
    assert r"Global\_results \& more" in tex
    body = [line for line in tex.splitlines() if line.endswith(r"\\") and not line.startswith(" &")]
    columns = {line.count(" & ") for line in body if "multicolumn" not in line}
    assert columns == {6}  # every row: label + 2 datasets x 3 metrics


def test_setting_tables_for_sweep_axes():
    rows = [final_row("gopre", "m360", "bonsai", s, 21.0 + k + 0.1 * s, 0.6, None,
                      setting=f"protocol.probes={k}", per_candidate_ms=100.0 + 10 * k,
                      selection_seconds=5.0 + k) for k in (1, 2) for s in (0, 1)]
    from pipeline.report.report import episode_tables
    table = episode_tables(pd.DataFrame(rows), "Table 5")[0]
    assert table.rows == ["protocol.probes=1", "protocol.probes=2"]
    assert table.cells[("protocol.probes=2", ("", "psnr"))].rank == 1
    assert table.cells[("protocol.probes=1", ("", "per_candidate_ms"))].rank == 1  # lower is better


def test_report_writes_tables_figures_and_the_runs_it_used(records, tmp_path):
    path = tmp_path / "records.parquet"
    records.to_parquet(path)
    summary = make_report(path, tmp_path / "out")
    assert summary["runs"] == len(records[records["kind"] == "final"]) and summary["failed"] == 1
    series = summary["figures"]["psnr_vs_views.png"]["lego"]
    assert set(series) == {"gopre", "random"}
    assert series["gopre"] == [[2, 3, 4], [13.0, 16.0, 19.0]]
    assert (tmp_path / "out" / "figures" / "psnr_vs_views.png").stat().st_size > 1000
    assert (tmp_path / "out" / "figures" / "psnr_vs_views.pdf").read_bytes().startswith(b"%PDF")  # vector
    report = (tmp_path / "out" / "report.md").read_text()
    assert "averages the curve's test views" in report
    assert "gopre-blender-lego-0-" in report and "FAILED" in report  # traceable to config hashes
    assert re.search(r"seeds \[0, 1\]", report)


def test_sparsification_figure_and_ause_table(tmp_path):
    rows = []
    for name, curve, a in (("gopre", [20, 21, 22], 0.1), ("random", [20, 20, 20], 0.5), ("oracle", [20, 22, 24], 0.0)):
        base = {**final_row("gopre", "blender", "lego", 0, None, None), "job_kind": "uncertainty"}
        rows += [{**base, "kind": "sparsification", "uncertainty_method": name, "fraction": f, "psnr": v}
                 for f, v in zip((0.0, 0.1, 0.2), curve)]
        rows.append({**base, "kind": "ause", "uncertainty_method": name, "ause": a})
    rows.append({**final_row("gopre", "blender", "lego", 0, 20.0, None), "job_kind": "uncertainty"})
    path = tmp_path / "records.parquet"
    pd.DataFrame(rows).to_parquet(path)
    summary = make_report(path, tmp_path / "out")
    assert set(summary["figures"]["sparsification.png"]) == {"gopre", "random", "oracle"}
    assert "**0.000**" in summary["tables"] and "<ins>0.100</ins>" in summary["tables"]
    # two scenes: one panel each (the paper's Fig. 7), each scene's own curve, not their mean
    other = pd.DataFrame(rows).assign(scene="bonsai", dataset="colmap")
    other.loc[other["kind"] == "sparsification", "psnr"] += 5.0
    pd.concat([pd.DataFrame(rows), other]).to_parquet(path)
    series = make_report(path, tmp_path / "out2")["figures"]["sparsification.png"]
    assert set(series) == {f"{s}/{m}" for s in ("lego", "bonsai") for m in ("gopre", "random", "oracle")}
    assert series["bonsai/gopre"][1] == [25.0, 26.0, 27.0] and series["lego/gopre"][1] == [20.0, 21.0, 22.0]


def test_missing_records_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no records file"):
        make_report(tmp_path, tmp_path / "out")


def test_a_degraded_job_gets_a_note_under_its_table_and_in_the_run_list(records, tmp_path):
    records = records.assign(degraded=False, curve_psnr_drop=0.1)
    bad = (records["method"] == "random") & (records["scene"] == "bonsai") & (records["kind"] == "final")
    records.loc[bad, ["degraded", "curve_psnr_drop"]] = [True, 18.47]
    path = tmp_path / "records.parquet"
    records.to_parquet(path)
    make_report(path, tmp_path / "out")
    table = (tmp_path / "out" / "table.md").read_text()
    assert "1 job(s) in these cells ended on a degraded model" in table
    assert "random on bonsai (seed 0): final PSNR 18.47 dB below its last round" in table
    assert "degraded" in (tmp_path / "out" / "runs.csv").read_text().splitlines()[0]
    assert "18.47" in (tmp_path / "out" / "table.tex").read_text()


def test_qualitative_grid_shows_the_ground_truth_once_then_a_column_per_method(tmp_path):
    """Render artifacts are [truth | render]; the grid has one row per test view, the truth in the
    first column only, then each method's render."""
    from PIL import Image

    from pipeline.report.figures import qualitative_grid
    truth = {v: np.full((8, 8, 3), 40 * v, np.uint8) for v in (1, 2)}
    renders = {}
    for k, method in enumerate(("gopre", "random")):
        folder = tmp_path / method
        folder.mkdir()
        for v, t in truth.items():
            Image.fromarray(np.concatenate([t, np.full((8, 8, 3), 200 + k, np.uint8)], 1)).save(
                folder / f"test_{v:04d}.png")
        renders[method] = sorted(folder.glob("*.png"))
    layout = qualitative_grid(renders, tmp_path / "grid.png")
    assert layout == {"columns": ["ground truth", "gopre", "random"], "rows": ["test_0001", "test_0002"]}
    assert (tmp_path / "grid.png").stat().st_size > 1000


def test_curves_get_a_panel_per_scene_and_setting():
    from pipeline.report.figures import psnr_vs_views
    import tempfile
    rows = [{**final_row(m, "blender", "lego", 0, p + (m == "gopre") + (5 if st.endswith("goal") else 0), 0.5,
                         setting=st), "kind": "round", "num_views": n}
            for m in ("gopre", "random") for st in ("protocol.kind=global", "protocol.kind=goal")
            for n, p in ((2, 10.0), (3, 12.0))]
    with tempfile.TemporaryDirectory() as tmp:
        series = psnr_vs_views(pd.DataFrame(rows), Path(tmp) / "c.png")
    assert set(series) == {"lego, protocol.kind=global", "lego, protocol.kind=goal"}
    assert series["lego, protocol.kind=goal"]["gopre"] == ([2, 3], [16.0, 18.0])  # not mixed with global


def test_a_method_has_one_colour_in_every_panel(tmp_path):
    """Methods appear in a different order per panel: the colours must still match the legend."""
    import matplotlib.pyplot as plt

    from pipeline.report import figures
    rows = [{**final_row(m, "blender", sc, 0, 10.0 + i, 0.5), "kind": "round", "num_views": 2}
            for sc, order in (("a", ("gopre", "random")), ("b", ("random", "gopre"))) for i, m in enumerate(order)]
    seen = {}
    real_plot = plt.Axes.plot

    def spy(ax, *args, **kwargs):
        seen.setdefault(kwargs["label"], set()).add(kwargs["color"])
        return real_plot(ax, *args, **kwargs)
    plt.Axes.plot = spy
    try:
        figures.psnr_vs_views(pd.DataFrame(rows), tmp_path / "c.png")
    finally:
        plt.Axes.plot = real_plot
    assert all(len(c) == 1 for c in seen.values()) and seen["gopre"] != seen["random"]


def test_cells_that_print_the_same_value_share_a_mark_in_both_formats():
    rows = [{"method": m, "dataset": "d", "seed": 0, "psnr": v} for m, v in
            [("a", 23.301), ("b", 23.298), ("c", 22.0)]]  # a and b both print 23.30
    table = build_table(pd.DataFrame(rows), "T", "method", "dataset", ["psnr"])
    md, tex = to_markdown(table), to_latex(table)
    assert md.count("**23.30**") == 2 and "<ins>22.00</ins>" in md
    assert tex.count(r"\best{23.30}") == 2 and r"\second{22.00}" in tex


def test_latex_uses_math_minus_captions_the_content_and_sets_notes_apart():
    rows = [{"method": m, "dataset": "d", "seed": 0, "psnr": v, "lpips": float("nan"),
             "lpips_status": "LPIPS (vgg) unavailable: ModuleNotFoundError: No module named 'lpips'"}
            for m, v in [("a", -1.5), ("b", 2.0)]]
    tex = to_latex(build_table(pd.DataFrame(rows), "sweep_x", "method", "dataset", ["psnr", "lpips"]))
    assert r"\second{-1.50}" in tex and "& -1.50" not in tex  # the macro sets it in math: a math minus
    assert r"\caption{sweep\_x: PSNR, LPIPS per method, one seed per cell (no spread)" in tex  # not "std"
    two_seeds = pd.DataFrame([{**r, "seed": s} for r in rows for s in (0, 1)]).assign(psnr_auc=1.0)
    tex2 = to_latex(build_table(two_seeds, "s", "method", "dataset", ["psnr", "psnr_auc"]))
    assert r"mean $\pm$ std over 2 seeds" in tex2
    assert "PSNR area: the area under the PSNR-vs-views curve" in tex2 and "PSNR area:" not in tex
    assert r"\label{tab:sweep-x}" in tex
    assert "ModuleNotFoundError" not in tex and "lpips package or its pretrained weights" in tex
    after = tex.split(r"\usebox{\gopretablebox}\fi")[1]  # the notes follow the (fitted) table
    assert after.lstrip().startswith(r"\par\smallskip") and r"\parbox{\linewidth}" in after



def test_the_latex_tables_compile_with_pdflatex_without_overfull_lines(records, tmp_path):
    import shutil
    import subprocess
    if shutil.which("pdflatex") is None:
        pytest.skip("pdflatex is not installed (Debian: apt-get install texlive-latex-recommended)")
    no_lpips = records.assign(lpips=float("nan"), lpips_status="LPIPS (vgg) unavailable: "
                              "ModuleNotFoundError: No module named 'lpips'")  # a note under the table
    make_report(records_path(no_lpips, tmp_path), tmp_path / "out")
    tex = (tmp_path / "out" / "table.tex").read_text()
    assert r"\begin{tabular}" in tex and "Delta" in tex  # the main and the paired table
    doc = tmp_path / "doc.tex"
    doc.write_text("\\documentclass{article}\n\\usepackage{booktabs}\n\\usepackage{graphicx}\n\\begin{document}\n"
                   f"{tex}\n\\end{{document}}\n")
    run = subprocess.run(["pdflatex", "-interaction=nonstopmode", "-halt-on-error", doc.name],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    log = (tmp_path / "doc.log").read_text(errors="replace")
    assert run.returncode == 0, log[-2000:]
    assert "Overfull \\hbox" not in log, [ln for ln in log.splitlines() if "Overfull" in ln]
    assert (tmp_path / "doc.pdf").stat().st_size > 0
    # the caption's promise, read off the PDF: the best cell is set in a bold font, the third in an
    # italic one (\textbf{$26.50$} set it in the upright roman: the marks were invisible)
    fonts = pdf_text_by_font(tmp_path / "doc.pdf")
    bold = "".join(text for font, text in fonts.items() if "CMBX" in font.upper())
    italic = "".join(text for font, text in fonts.items() if "CMTI" in font.upper() or "CMMI" in font.upper())
    digits = lambda text: "".join(c for c in text if c.isdigit())  # noqa: E731 (the point comes from a math font)
    assert "2650" in digits(bold), fonts  # gopre's PSNR on blender, 26.50: the best
    assert "2300" in digits(italic), fonts  # coverage's, 23.00: the third
    regular = "".join(text for font, text in fonts.items() if "CMR" in font.upper())
    assert "2650" not in digits(regular)


def pdf_text_by_font(path) -> dict[str, str]:
    """The text of a PDF's first page, joined per font (the font's BaseFont name)."""
    pypdf = pytest.importorskip("pypdf")
    chunks: dict[str, str] = {}

    def visit(text, cm, tm, font, size):
        if text and font is not None:
            name = str(font.get("/BaseFont", ""))
            chunks[name] = chunks.get(name, "") + text
    pypdf.PdfReader(str(path)).pages[0].extract_text(visitor_text=visit)
    return chunks


def records_path(frame, tmp_path):
    frame.to_parquet(tmp_path / "records.parquet")
    return tmp_path / "records.parquet"


def test_several_sweeps_are_reported_as_one_table_and_a_twice_run_episode_is_refused(tmp_path):
    from pipeline.report.report import combine_records
    study = pd.DataFrame([{**final_row(m, "blender", "lego", s, p + s, 0.9), "sweep": "study",
                           "job_index": i} for i, (m, p, s) in
                          enumerate([("gopre", 25.0, 0), ("random", 21.0, 0), ("gopre", 25.0, 1)])])
    extra = pd.DataFrame([{**final_row("cover", "blender", "lego", 0, 24.0, 0.9), "sweep": "preset",
                           "job_index": 0}])
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    combined = combine_records([records_path(study, tmp_path / "a"),
                                records_path(extra, tmp_path / "b")])
    assert list(combined["method"]) == ["gopre", "random", "gopre", "cover"]  # sweep by sweep
    table = build_table(combined[combined["kind"] == "final"], "t", "method", None, ["psnr"])
    assert table.rows == ["gopre", "random", "cover"]
    twice = pd.DataFrame([{**final_row("random", "blender", "lego", 0, 20.0, 0.9),
                           "sweep": "again", "job_index": 0}])
    (tmp_path / "c").mkdir()
    with pytest.raises(ValueError, match=r"method=random.*finished in more than one.*'again', 'study'"):
        combine_records([records_path(study, tmp_path / "a"), records_path(twice, tmp_path / "c")])


def test_a_sweep_gets_one_qualitative_grid_per_scene_from_its_first_seed_and_setting(tmp_path):
    """Paper Fig. 5 has a panel per dataset: each scene its own grid, columns = methods (the first
    seed, the scene's first setting), not the first scene only nor a column per setting."""
    from PIL import Image

    from pipeline.report.report import make_figures
    sweep = tmp_path / "sweep"
    rows = []
    for scene, shade in (("lego", 50), ("bonsai", 150)):
        for method in ("gopre", "random"):
            for seed in (0, 1):
                for setting in ("protocol.kind=global", "protocol.kind=goal"):
                    row = final_row(method, "d", scene, seed, 20.0, 0.5, setting=setting)
                    folder = sweep / "jobs" / row["config_hash"] / "artifacts" / "renders"
                    folder.mkdir(parents=True)
                    render = np.full((8, 8, 3), shade + 10 * seed + (setting.endswith("goal")), np.uint8)
                    Image.fromarray(np.concatenate([np.zeros((8, 8, 3), np.uint8), render], 1)).save(
                        folder / "test_0001.png")
                    rows.append(row)
    made = make_figures(pd.DataFrame(rows), sweep, tmp_path / "out")
    assert made["qualitative.png"]["columns"] == made["qualitative_bonsai.png"]["columns"] == \
        ["ground truth", "gopre", "random"]
    from pipeline.report.report import grid_images
    chosen = grid_images(sweep, pd.DataFrame(rows), "renders", "bonsai")
    shades = {m: int(np.asarray(Image.open(f[0]))[0, 8, 0]) for m, f in chosen.items()}
    assert shades == {"gopre": 150, "random": 150}  # bonsai, seed 0, the first setting (global)


def test_each_methods_selection_cpu_time_is_tabled_beside_its_quality(tmp_path):
    """Mean over rounds is in the final row; the table is the mean over scenes then seeds, per
    dataset, lower ranked better; a sweep with no selection times gets no such table."""
    rows = []
    cpu = {("gopre", 0): (4.0, 6.0), ("gopre", 1): (5.0, 7.0), ("cover", 0): (1.0, 2.0),
           ("cover", 1): (3.0, 2.0)}
    for (method, seed), (lego, chair) in cpu.items():
        rows.append(final_row(method, "blender", "lego", seed, 25.0, 0.9, selection_cpu_seconds=lego))
        rows.append(final_row(method, "blender", "chair", seed, 24.0, 0.9, selection_cpu_seconds=chair))
    rows.append(final_row("random", "blender", "lego", 0, 20.0, 0.9, selection_cpu_seconds=0.001))
    rows += [{**r, "kind": "round", "num_views": n, "psnr": r["psnr"] - 4 + n}
             for r in list(rows) for n in (2, 3)]  # the curves the paired tables read
    frame = pd.DataFrame(rows)
    path = tmp_path / "records.parquet"
    frame.to_parquet(path)
    make_report(path, tmp_path / "out")
    table = (tmp_path / "out" / "table.md").read_text()
    section = table[table.index("selection CPU seconds per round"):]
    assert "| gopre | _5.50 ± 0.71_ |" in section  # seeds: (4 + 6) / 2 = 5, (5 + 7) / 2 = 6
    assert "| cover | <ins>2.00 ± 0.71</ins> |" in section  # 1.5 and 2.5
    assert "| random | **0.00** |" in section
    assert "\\begin{tabular}" in (tmp_path / "out" / "table.tex").read_text()
    frame.drop(columns="selection_cpu_seconds").to_parquet(path)
    make_report(path, tmp_path / "plain")
    assert "selection CPU" not in (tmp_path / "plain" / "table.md").read_text()


def test_each_scene_gets_its_own_paired_table_with_its_own_pairs(tmp_path):
    """Five seeds on two scenes: the pooled table has 10 pairs, each scene's table its own 5 and
    its own mean difference, so a scene's verdict is drawn from that scene alone."""
    from pipeline.report.report import episode_tables, render_markdown
    gaps = {"lego": [0.5, 0.6, 0.4, 0.7, 0.5], "bonsai": [-0.2, -0.1, -0.3, -0.2, -0.4]}
    rows = []
    for scene, per_seed in gaps.items():
        for seed, gap in enumerate(per_seed):
            rows.append(final_row("gopre", "d", scene, seed, 20.0 + seed + gap, 0.8))
            rows.append(final_row("random", "d", scene, seed, 20.0 + seed, 0.8))
    tables = {t.title: t for t in episode_tables(pd.DataFrame(rows), "t")
              if "paired differences" in t.title}
    assert list(tables) == ["t: paired differences against gopre",
                            "t, lego only: paired differences against gopre",
                            "t, bonsai only: paired differences against gopre"]
    assert tables["t: paired differences against gopre"].rows["random"]["psnr"].n == 10
    for scene, per_seed in gaps.items():
        c = tables[f"t, {scene} only: paired differences against gopre"].rows["random"]["psnr"]
        assert c.n == 5 and c.mean_difference == pytest.approx(-np.mean(per_seed))
    text = render_markdown(tables["t, bonsai only: paired differences against gopre"])
    assert "random better" in text  # random - gopre > 0 on every bonsai seed: the scene's own verdict


def test_a_figure_regenerated_is_the_same_file(tmp_path):
    """Published figures are tracked: regenerating a report must not rewrite its PDFs (a creation
    date in them did, every time)."""
    import time

    import matplotlib.pyplot as plt

    from pipeline.report.figures import save_figure
    digests = []
    for k in range(2):
        fig, ax = plt.subplots()
        ax.plot([0, 1], [1, 2])
        save_figure(fig, tmp_path / f"f{k}.png")
        digests.append((tmp_path / f"f{k}.pdf").read_bytes())
        time.sleep(1.1)  # the PDF date has one-second resolution
    assert digests[0] == digests[1]


def test_sweeps_compared_by_sweep_get_a_grid_of_one_method_under_each_sweep(tmp_path):
    """``--by-sweep``: the grid's columns are the reference method (gopre) in each sweep, each
    render read from its own sweep's folder, not the first sweep's methods again; a scene only
    one sweep ran gets none."""
    from PIL import Image

    from pipeline.report.report import combine_records, make_figures
    sources = []
    for name, shade in (("reset", 40), ("noreset", 200)):
        folder = tmp_path / name
        rows = []
        jobs = [("random", "bonsai", 0), ("gopre", "bonsai", 7)] + ([("gopre", "lego", 3)] if name == "reset" else [])
        for i, (method, scene, offset) in enumerate(jobs):
            row = {**final_row(method, "d", scene, 0, 20.0, 0.5), "sweep": name, "job_index": i,
                   "config_hash": f"{method}-{scene}-same-hash"}  # the same job in both sweeps
            renders = folder / "jobs" / row["config_hash"] / "artifacts" / "renders"
            renders.mkdir(parents=True)
            image = np.concatenate([np.zeros((8, 8, 3), np.uint8), np.full((8, 8, 3), shade + offset, np.uint8)], 1)
            Image.fromarray(image).save(renders / "test_0001.png")
            rows.append(row)
        sources.append(records_path(pd.DataFrame(rows), folder))
    frame = combine_records(sources, by_sweep=True)
    made = make_figures(frame, tmp_path / "reset", tmp_path / "out")
    assert made["qualitative.png"]["columns"] == ["ground truth", "gopre (reset)", "gopre (noreset)"]
    assert "qualitative_lego.png" not in made  # one sweep's scene: its own report has the grid
    from pipeline.report.report import grid_images
    chosen = grid_images(tmp_path / "reset", frame[frame["kind"] == "final"], "renders", "bonsai")
    assert {k: int(np.asarray(Image.open(f[0]))[0, 8, 0]) for k, f in chosen.items()} == \
        {"gopre (reset)": 47, "gopre (noreset)": 207}


def test_a_report_regenerated_into_its_folder_keeps_only_its_own_figures(tmp_path):
    """An earlier report's grid of a scene the new records lack is removed (PNG and PDF); what is
    not a figure, or outside figures/, stays."""
    from PIL import Image

    from pipeline.report.report import make_report
    sweep = tmp_path / "sweep"
    rows = []
    for i, scene in enumerate(("lego", "bonsai")):
        row = {**final_row("gopre", "d", scene, 0, 20.0, 0.5), "job_index": i}
        renders = sweep / "jobs" / row["config_hash"] / "artifacts" / "renders"
        renders.mkdir(parents=True)
        Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(renders / "test_0001.png")
        rows.append(row)
    records_path(pd.DataFrame(rows), sweep)
    out = tmp_path / "report"
    first = make_report(sweep, out)
    assert {"qualitative.png", "qualitative_bonsai.png"} <= set(first["figures"]) and not first["removed_figures"]
    (out / "figures" / "notes.txt").write_text("mine")
    (out / "keep.png").write_bytes(b"not the report's")
    frame = pd.DataFrame(rows[:1])
    second = make_report(sweep, out, frame)
    assert second["removed_figures"] == ["qualitative_bonsai.pdf", "qualitative_bonsai.png"]
    assert sorted(p.name for p in (out / "figures").iterdir()) == ["notes.txt", "qualitative.pdf", "qualitative.png"]
    assert (out / "keep.png").exists()


def test_no_images_leaves_every_picture_of_the_scene_out_of_the_report(tmp_path, capsys):
    """``--no-images`` (a capture whose license keeps its photos out of a published report): no
    grid of ground truth and renders, the curves still drawn, a grid an earlier report drew into
    the folder removed, and the report says why there is none."""
    from PIL import Image

    from pipeline.cli.report import main
    sweep = tmp_path / "sweep"
    rows = []
    for seed in (0, 1):
        row = {**final_row("gopre", "d", "alexander", seed, 20.0, 0.5), "job_index": seed}
        renders = sweep / "jobs" / row["config_hash"] / "artifacts" / "renders"
        renders.mkdir(parents=True)
        Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(renders / "test_0001.png")
        rows += [row, {**row, "kind": "round", "num_views": 4, "iteration": 100, "test_psnr": 18.0},
                 {**row, "kind": "round", "num_views": 5, "iteration": 225, "test_psnr": 19.0}]
    records_path(pd.DataFrame(rows), sweep)
    out = tmp_path / "report"
    assert main([str(sweep), "--out", str(out)]) == 0
    assert (out / "figures" / "qualitative.png").exists()
    assert main([str(sweep), "--out", str(out), "--no-images"]) == 0
    assert sorted(p.name for p in (out / "figures").iterdir()) == ["psnr_vs_views.pdf", "psnr_vs_views.png"]
    report = (out / "report.md").read_text()
    assert "qualitative" not in report and "made with `--no-images`" in report
    assert "removed from" in capsys.readouterr().out


def test_a_grid_beside_an_outside_result_reads_the_sweeps_renders_and_skips_the_outside_row(tmp_path):
    """An outside method's rows (a result file: no job folder, no ``sweep_dir``, no config hash)
    get an empty column; the sweep's rows still read their renders. Broke CI once (a Path of NaN)."""
    from PIL import Image

    from pipeline.report.report import grid_images
    sweep_row = {**final_row("gopre", "d", "bonsai", 0, 20.0, 0.5), "config_hash": "abc", "sweep_dir": str(tmp_path)}
    outside_row = {**final_row("mean_colour", "d", "bonsai", 0, 18.0, 0.5), "config_hash": np.nan,
                   "sweep_dir": np.nan}
    renders = tmp_path / "jobs" / "abc" / "artifacts" / "renders"
    renders.mkdir(parents=True)
    Image.fromarray(np.zeros((8, 16, 3), np.uint8)).save(renders / "test_0001.png")
    frame = pd.DataFrame([sweep_row, outside_row])
    assert grid_images(None, frame, "renders") == {"gopre": [renders / "test_0001.png"], "mean_colour": []}
    assert grid_images(tmp_path, frame.drop(columns="sweep_dir"), "renders")["gopre"] == [renders / "test_0001.png"]


def test_a_grid_of_records_without_a_setting_column_is_one_column_per_method(tmp_path):
    """Records written before settings existed (no ``setting`` column), from two sweeps: the
    grid is drawn, not a KeyError."""
    from pipeline.report.report import grid_images
    rows = [{**final_row(m, "d", "bonsai", 0, 20.0, 0.5), "config_hash": m, "sweep": sweep}
            for m, sweep in (("gopre", "a"), ("random", "b"))]
    frame = pd.DataFrame(rows).drop(columns="setting", errors="ignore")
    assert set(grid_images(tmp_path, frame, "renders")) == {"gopre", "random"}


def test_psnr_against_cumulative_selection_time_by_hand(tmp_path):
    """A round's point sits at the selection seconds its job spent before it was evaluated; the
    line is the mean over seeds of both coordinates."""
    from pipeline.report.figures import cumulative_selection_seconds, psnr_vs_selection_time
    rows = []
    for seed, (times, psnrs) in enumerate((([1.0, 2.0, None], [10.0, 11.0, 12.0]), ([3.0, 4.0, None], [12.0, 13.0, 14.0]))):
        for k, (t, p) in enumerate(zip(times, psnrs)):
            rows.append({"sweep": "s", "config_hash": f"h{seed}", "scene": "lego", "setting": "", "method": "gopre",
                         "num_views": 2 + k, "psnr": p, "selection_cpu_seconds": t, "selection_seconds": 99.0})
    rounds = pd.DataFrame(rows).iloc[::-1]  # rows in any order
    assert cumulative_selection_seconds(rounds, "selection_cpu_seconds").sort_index().tolist() == [0, 1, 3, 0, 3, 7]
    series = psnr_vs_selection_time(rounds, tmp_path / "t.png")
    assert series["lego"]["gopre"] == ([0.0, 2.0, 5.0], [11.0, 12.0, 13.0])
    assert (tmp_path / "t.png").exists()
    assert psnr_vs_selection_time(rounds.drop(columns=["selection_cpu_seconds", "selection_seconds"]), tmp_path / "n.png") is None


def test_fig7_extended_draws_each_methods_mean_relative_curve_and_the_oracle(tmp_path):
    """Two seeds of one method on one scene, by hand: the plotted curve is the mean over seeds of
    each job's curve over its own error of all pixels (its random curve)."""
    from pipeline.report import figures
    from pipeline.report.pixel_curves import COLUMNS, relative
    rows = []
    for seed, scale in ((0, 2.0), (1, 4.0)):
        for error in ("mae", "rmse", "dssim"):
            for f, by, oracle in ((0.0, 1.0, 1.0), (0.5, 0.8, 0.4)):
                rows.append(("bonsai", "gopre", seed, error, f, scale * by, scale * oracle, scale * 1.0))
    curves = relative(pd.DataFrame(rows, columns=COLUMNS))
    assert curves["random"].tolist() == [1.0] * len(curves)
    series = figures.pixel_sparsification(curves, {("bonsai", "gopre", "mae"): 0.1}, tmp_path / "f.png")
    assert series["bonsai/mae/gopre"] == ([0.0, 0.5], [1.0, 0.8])  # not (2*0.8 + 4*0.8) / 2 = 2.4
    assert set(series) == {f"bonsai/{e}/gopre" for e in ("mae", "rmse", "dssim")} and (tmp_path / "f.png").exists()
