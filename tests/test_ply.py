"""Standard 3DGS files: gsplat's exporter writes, our reader reads back identical parameters and
renders; the INRIA layout (channel-major f_rest, logit opacity, log scales, w-first quaternion)
is checked on bytes read with struct, not with our reader."""

import struct

import pytest
import torch

from pipeline.splat import ply, render
from pipeline.splat.gaussians import Gaussians
from pipeline.splat.scenes import orbit_cameras, random_scene

pytest.importorskip("gsplat")


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_gives_identical_parameters_and_renders(tmp_path, degree):
    g = random_scene(200, seed=degree, sh_degree=degree)
    path = ply.save(g, tmp_path / "model.ply")
    back = ply.load(path)
    for name, value in g.params().items():
        assert torch.equal(getattr(back, name), value.float()), name
    cams = orbit_cameras(2, 40, 32)
    assert torch.equal(render(back, cams).rgb, render(g, cams).rgb)


def test_the_file_has_the_inria_layout(tmp_path):
    shn = torch.arange(3 * 3, dtype=torch.float32).reshape(1, 3, 3) + 100  # [1, K=3, 3]: coefficient k, channel c
    g = Gaussians(means=torch.tensor([[1.0, 2.0, 3.0]]), log_scales=torch.tensor([[-1.0, -2.0, -3.0]]),
                  quats=torch.tensor([[0.5, 0.1, 0.2, 0.3]]), logit_opacities=torch.tensor([0.7]),
                  sh0=torch.tensor([[[10.0, 11.0, 12.0]]]), shN=shn)
    data = ply.save(g, tmp_path / "one.ply").read_bytes()
    header, body = data.split(b"end_header\n")
    names = [line.split()[-1] for line in header.decode().splitlines() if line.startswith("property")]
    values = dict(zip(names, struct.unpack("<" + "f" * len(names), body)))
    assert [values[f"f_rest_{i}"] for i in range(9)] == [100, 103, 106, 101, 104, 107, 102, 105, 108]
    assert [values[n] for n in ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2")] == [1, 2, 3, 10, 11, 12]
    assert values["opacity"] == pytest.approx(0.7) and values["scale_2"] == -3.0
    assert [values[f"rot_{i}"] for i in range(4)] == pytest.approx([0.5, 0.1, 0.2, 0.3])


def test_viewer_formats_are_written_and_bad_files_are_named(tmp_path):
    g = random_scene(300, seed=1, sh_degree=1)
    assert ply.save(g, tmp_path / "m.splat", "splat").stat().st_size == 300 * 32  # 32 bytes per splat
    compressed = ply.save(g, tmp_path / "m.compressed.ply", "ply_compressed")
    with pytest.raises(ValueError, match=r"a compressed PLY \(chunk element\) is a viewer format"):
        ply.load(compressed)
    with pytest.raises(ValueError, match="export format must be one of"):
        ply.export_bytes(g, "obj")
    (tmp_path / "bad.ply").write_bytes(b"hello")
    with pytest.raises(ValueError, match=r"bad.ply: not a PLY file"):
        ply.load(tmp_path / "bad.ply")
    whole = (tmp_path / "m.ply")
    ply.save(g, whole)
    (tmp_path / "cut.ply").write_bytes(whole.read_bytes()[:-10])
    with pytest.raises(ValueError, match=r"cut.ply: truncated"):
        ply.load(tmp_path / "cut.ply")


def test_export_cli_from_a_checkpoint_a_job_folder_and_a_ply(tmp_path, capsys):
    """A checkpoint exports the model of its last round at that round's SH degree; a job folder
    its final model.ply; errors exit 1 naming the source."""
    from pipeline.active import tiny_episode
    from pipeline.active.episode import Episode
    from pipeline.active.checkpoint import save_checkpoint
    from pipeline.data.load import load_scene
    from pipeline.data.synthetic import generate
    from pipeline.cli.export import main
    cfg = tiny_episode(strategy="random")
    scene = load_scene(generate(tmp_path / "scene", seed=0, size=32, n_train=8, n_test=4), width=32)
    ep = Episode(scene, cfg)
    ep.train(40, progress=False)  # below the first SH step: degree 0 of the stored 1
    save_checkpoint(tmp_path / "job" / "checkpoint", ep.state("key"))
    assert main([str(tmp_path / "job"), "--out", str(tmp_path / "a.ply")]) == 0
    exported = ply.load(tmp_path / "a.ply")
    expected = ep.trainer.rendered_gaussians
    assert exported.sh_degree == 0 == ep.trainer.active_sh_degree < cfg.fit.sh_degree
    for name, value in expected.params().items():
        assert torch.equal(getattr(exported, name), value), name
    ply.save(expected, tmp_path / "job" / "artifacts" / "model.ply")  # a finished job: its final model
    assert main([str(tmp_path / "job"), "--format", "splat"]) == 0
    assert (tmp_path / "job" / "model.splat").stat().st_size == 32 * len(expected)
    assert main([str(tmp_path / "a.ply"), "--format", "ply_compressed"]) == 0
    assert (tmp_path / "a-export.compressed.ply").exists()
    capsys.readouterr()
    assert main([str(tmp_path / "nope")]) == 1
    assert "nope: no such file or folder" in capsys.readouterr().err


def test_an_episode_starts_from_a_ply_with_its_sh_fitted_to_the_degree(tmp_path):
    from pipeline.active import tiny_episode
    from pipeline.active.episode import Episode
    from pipeline.data.load import load_scene
    from pipeline.data.synthetic import generate
    scene = load_scene(generate(tmp_path / "scene", seed=0, size=32, n_train=8, n_test=4), width=32)
    source = random_scene(150, seed=4, sh_degree=3)
    ply.save(source, tmp_path / "init.ply")
    cfg = tiny_episode(strategy="random", init=f"ply:{tmp_path / 'init.ply'}")  # tiny: degree 1
    init = Episode(scene, cfg).init
    assert torch.equal(init.means, source.means) and init.sh_degree == cfg.fit.sh_degree == 1
    assert torch.equal(init.shN, source.shN[:, :3])
    low = random_scene(20, seed=5, sh_degree=0)
    ply.save(low, tmp_path / "low.ply")
    padded = Episode(scene, cfg.with_changes(init=f"ply:{tmp_path / 'low.ply'}")).init
    assert padded.shN.shape == (20, 3, 3) and padded.shN.abs().sum() == 0
    with pytest.raises(ValueError, match="init must be 'ply:PATH' or null, got 'init.ply'"):
        cfg.with_changes(init="init.ply")


def test_ascii_ply_with_extra_colour_and_normal_properties_reads_the_same_model(tmp_path):
    """Other tools write ASCII PLY and add uchar colours and normals: the 3DGS properties are what
    counts (the file is rewritten by plyfile, not by our code)."""
    import numpy as np
    from plyfile import PlyData, PlyElement
    g = random_scene(50, seed=2, sh_degree=1)
    binary = PlyData.read(str(ply.save(g, tmp_path / "m.ply")))["vertex"].data
    extra = [("nx", "f4"), ("ny", "f4"), ("nz", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    table = np.zeros(len(binary), dtype=binary.dtype.descr + extra)
    for name in binary.dtype.names:
        table[name] = binary[name]
    table["red"] = 200
    PlyData([PlyElement.describe(table, "vertex")], text=True).write(str(tmp_path / "ascii.ply"))
    assert (tmp_path / "ascii.ply").read_bytes().startswith(b"ply\nformat ascii 1.0")
    back = ply.load(tmp_path / "ascii.ply")
    for name, value in g.params().items():
        assert torch.allclose(getattr(back, name), value.float(), rtol=1e-6, atol=1e-7), name
    big = PlyData([PlyElement.describe(table.astype(table.dtype.newbyteorder(">")), "vertex")], byte_order=">")
    big.write(str(tmp_path / "big.ply"))
    assert torch.equal(ply.load(tmp_path / "big.ply").means, g.means.float())



def test_spz_round_trip_keeps_the_model_to_its_quantisation(tmp_path, capsys):
    """SPZ (Niantic) through gsply: 12 fractional bits for positions, 8-bit scales, opacities and
    colours, smallest-three quaternions. Read back (by gsply's reader, not ours) the parameters
    are within those steps and the renders agree to well above 30 dB."""
    pytest.importorskip("gsply")
    from pipeline.cli.export import main
    g = random_scene(400, seed=4, sh_degree=2)
    path = ply.save(g, tmp_path / "m.spz", "spz")
    assert path.stat().st_size < 0.4 * len(ply.export_bytes(g, "ply"))
    back = ply.load(path)
    assert len(back) == len(g) and back.sh_degree == 2
    assert (back.means - g.means).abs().max() <= 2 ** -12          # fixed point, 12 fractional bits
    assert (back.log_scales - g.log_scales).abs().max() <= 1 / 16 + 1e-6
    q, q_back = torch.nn.functional.normalize(g.quats, dim=-1), torch.nn.functional.normalize(back.quats, dim=-1)
    assert (q * q_back).sum(-1).abs().min() > 0.999                # the same rotation (q ~ -q)
    assert (torch.sigmoid(back.logit_opacities) - torch.sigmoid(g.logit_opacities)).abs().max() < 1 / 128
    cams = orbit_cameras(2, 48, 48)
    mse = (render(back, cams).rgb - render(g, cams).rgb).square().mean()
    assert -10 * torch.log10(mse) > 30
    ply.save(g, tmp_path / "m.ply")
    assert main([str(tmp_path / "m.ply"), "--format", "spz", "--out", str(tmp_path / "c.spz")]) == 0
    line = capsys.readouterr().out
    assert "c.spz: 400 Gaussians, SH degree 2, format spz" in line and "dropped" not in line
    assert main([str(tmp_path / "m.ply"), "--format", "ply_compressed", "--out", str(tmp_path / "c.ply")]) == 0
    assert "c.ply: 400 Gaussians" in capsys.readouterr().out  # what the compressed file holds


def test_a_splat_file_reads_back_as_what_it_holds(tmp_path):
    """The antimatter15 .splat keeps positions and scales as float32, colour and opacity in 8 bits
    (truncated), rotations in 8 bits and no SH beyond degree 0; reading it gives exactly that."""
    g = random_scene(200, seed=4, sh_degree=1)
    back = ply.load(ply.save(g, tmp_path / "m.splat", "splat"))
    assert len(back) == len(g) and back.sh_degree == 0
    # the exporter sorts rows: match them by position (exact float32)
    order = {tuple(p): i for i, p in enumerate(g.means.tolist())}
    idx = torch.tensor([order[tuple(p)] for p in back.means.tolist()])
    assert torch.equal(back.means, g.means[idx])
    assert torch.allclose(back.log_scales, g.log_scales[idx], atol=1e-5)
    c0 = 0.28209479177387814
    colour, colour_back = (0.5 + c0 * g.sh0[idx, 0]).clamp(0, 1), 0.5 + c0 * back.sh0[:, 0]
    assert ((colour - colour_back) >= -1e-6).all() and ((colour - colour_back) < 1 / 255 + 1e-6).all()
    alpha, alpha_back = torch.sigmoid(g.logit_opacities[idx]), torch.sigmoid(back.logit_opacities)
    inside = (alpha > 1 / 255) & (alpha < 254 / 255)
    assert ((alpha - alpha_back)[inside].abs() < 1 / 255 + 1e-6).all()
    q = g.quats[idx] / g.quats[idx].norm(dim=1, keepdim=True)
    assert ((q * back.quats).sum(1).abs() > 0.995).all()  # the same rotation, to 8 bits a component
    raw = (tmp_path / "m.splat").read_bytes()  # the format's spec: rotation byte b holds (b - 128) / 128
    rotation = torch.tensor([list(raw[32 * i + 28:32 * i + 32]) for i in range(len(back))], dtype=torch.float64)
    expected = (rotation - 128) / 128
    assert torch.allclose(back.quats.double(), expected / expected.norm(dim=1, keepdim=True), atol=1e-6)


def test_a_model_file_of_another_kind_is_refused_naming_the_formats_read(tmp_path):
    (tmp_path / "m.ksplat").write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match=r"m.ksplat: not a model file this reads; accepted: \.ply .*\.spz .*\.splat"):
        ply.load(tmp_path / "m.ksplat")
    (tmp_path / "cut.splat").write_bytes(b"\x00" * 33)
    with pytest.raises(ValueError, match="33 bytes is not a whole number of 32-byte .splat rows"):
        ply.load(tmp_path / "cut.splat")
