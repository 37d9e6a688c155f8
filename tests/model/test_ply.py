"""3DGS PLY export: the SH basis change is exact on fresh directions and in renders, files
round-trip, and an independent reader (plyfile) sees the standard fields."""

import re

import numpy as np
import pytest
import torch

from usplat_dr.model.ply import read_ply, sh_to_3dgs, write_ply
from usplat_dr.model.types import Gaussians
from usplat_dr.render import RasterSettings, rasterize
from usplat_dr.render.sh import sh_basis


def random_gaussians(g: int = 50, d_sh: int = 16, seed: int = 0) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(1, g, 3, generator=gen) * 0.3 + torch.tensor([0, 0, 3.0])
    a = torch.randn(1, g, 3, 3, generator=gen) * 0.05
    cov = a @ a.transpose(-1, -2) + 1e-4 * torch.eye(3)
    sh = torch.randn(1, g, 3, d_sh, generator=gen) * 0.3
    op = torch.rand(1, g, generator=gen) * 0.9 + 0.05
    return Gaussians(means=means, covariances=cov, harmonics=sh, opacities=op,
                     scales=torch.ones(1, g, 3), rotations=torch.zeros(1, g, 4))


def test_basis_change_is_exact_on_fresh_directions():
    # f(d) = sum_i c_i B_mvsplat_i(d) must equal sum_i c'_i B_3dgs_i(d) everywhere: checked on
    # 500 random directions not used to solve the basis change (float64, ~1e-13).
    rng = np.random.default_rng(1)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = torch.randn(1, 16, dtype=torch.float64)
    c_std = sh_to_3dgs(c[:, None])[:, 0]
    mv = np.stack(np.broadcast_arrays(*sh_basis(*d.T, 3, "mvsplat")), 1)
    std = np.stack(np.broadcast_arrays(*sh_basis(*d.T, 3, "3dgs")), 1)
    assert np.allclose(mv @ c[0].numpy(), std @ c_std[0].numpy(), atol=1e-10)


def test_converted_gaussians_render_the_same_image():
    g = random_gaussians()
    converted = sh_to_3dgs(g.harmonics)
    k = torch.tensor([[[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]]])
    args = (torch.eye(4)[None], k, torch.tensor([0.1]), torch.tensor([100.0]), (32, 32),
            torch.zeros(1, 3), g.means, g.covariances)
    a = rasterize(*args, g.harmonics, g.opacities, RasterSettings(sh_basis="mvsplat"))
    b = rasterize(*args, converted, g.opacities, RasterSettings(sh_basis="3dgs"))
    # float32 colour sums in two bases: ~1e-6
    assert torch.allclose(a.color, b.color, atol=1e-5)


def test_ply_round_trip_and_independent_reader(tmp_path):
    import plyfile

    g = random_gaussians(d_sh=9)  # degree 2: f_rest padded to the degree-3 layout
    path = write_ply(tmp_path / "g.ply", g)
    back = read_ply(path)
    # float32 storage of log-scales, logit opacities and quaternions: ~1e-6 relative
    assert torch.allclose(back["means"], g.means[0], atol=1e-6)
    assert torch.allclose(back["opacities"], g.opacities[0], atol=1e-5)
    assert torch.allclose(back["covariances"], g.covariances[0], rtol=1e-4, atol=1e-7)
    std = sh_to_3dgs(g.harmonics[0].double()).float()
    assert torch.allclose(back["harmonics"][..., :9], std, atol=1e-6)
    assert not back["harmonics"][..., 9:].any()

    ply = plyfile.PlyData.read(str(path))
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1",
                          "rot_2", "rot_3"]
    assert len(v.data) == 50
    assert np.allclose(v["x"], g.means[0, :, 0].numpy(), atol=1e-6)
    # the viewer's reading: sigmoid(opacity) and exp(scale)^2 = the covariance's eigenvalues
    assert np.allclose(1 / (1 + np.exp(-v["opacity"])), g.opacities[0].numpy(), atol=1e-5)
    eig = np.linalg.eigvalsh(g.covariances[0].double().numpy())
    s2 = np.sort(np.exp(2 * np.stack([v[f"scale_{i}"] for i in range(3)], 1)), 1)
    assert np.allclose(s2, eig, rtol=1e-4)


def graphdeco_file(path, g: int, degree: int, extra: bool, seed: int = 0):
    """A PLY as the graphdeco 3DGS code writes it (``GaussianModel.save_ply``), made with the
    independent writer plyfile: SH degree ``degree`` (3 (degree+1)^2 - 3 f_rest properties),
    optionally with properties other tools add (uchar colours, a double, an int)."""
    import plyfile

    rng = np.random.default_rng(seed)
    n_rest = 3 * ((degree + 1) ** 2 - 1)
    fields = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
              *[f"f_rest_{i}" for i in range(n_rest)], "opacity", "scale_0", "scale_1",
              "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    dtype = [(f, "f4") for f in fields]
    if extra:
        dtype = dtype[:3] + [("red", "u1"), ("green", "u1"), ("blue", "u1")] + dtype[3:] + [
            ("importance", "f8"), ("cluster", "i4")]
    data = np.zeros(g, dtype=dtype)
    for f in fields:
        data[f] = rng.normal(size=g)
    if extra:
        data["red"] = rng.integers(0, 255, g)
        data["importance"] = rng.normal(size=g)
        data["cluster"] = rng.integers(-5, 5, g)
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")]).write(str(path))
    return data


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("extra", [False, True])
def test_reads_graphdeco_files_of_every_sh_degree(tmp_path, degree, extra):
    data = graphdeco_file(tmp_path / "g.ply", 20, degree, extra, seed=degree)
    back = read_ply(tmp_path / "g.ply")
    k = (degree + 1) ** 2
    assert back["sh_degree"] == degree and back["harmonics"].shape == (20, 3, k)
    # f_rest is channel-major: coefficient j >= 1 of channel c is f_rest_{c (k-1) + j-1}
    for c in range(3):
        assert np.array_equal(back["harmonics"][:, c, 0].numpy(), data[f"f_dc_{c}"])
        for j in range(1, k):
            assert np.array_equal(back["harmonics"][:, c, j].numpy(),
                                  data[f"f_rest_{c * (k - 1) + j - 1}"])
    assert np.array_equal(back["means"].numpy(), np.stack([data[a] for a in "xyz"], 1))
    # the viewer's reading, in float64 from the stored values (float32 exp/sigmoid: ~1e-6)
    s = np.exp(np.stack([data[f"scale_{i}"] for i in range(3)], 1).astype(np.float64))
    assert np.allclose(back["scales"].numpy(), s, rtol=1e-6)
    op = 1 / (1 + np.exp(-data["opacity"].astype(np.float64)))
    assert np.allclose(back["opacities"].numpy(), op, atol=1e-6)
    # covariance = R diag(s^2) R^T with R from the normalised wxyz quaternion (float64 here)
    q = np.stack([data[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    r = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                 1).reshape(-1, 3, 3)
    cov = r @ (s[:, :, None] ** 2 * r.transpose(0, 2, 1))
    # float32 products of values up to e^(2*3): relative 1e-5 of the largest entry
    assert np.allclose(back["covariances"].numpy(), cov, rtol=1e-4,
                       atol=1e-5 * np.abs(cov).max())


def test_unreadable_plys_name_the_problem(tmp_path):
    data = graphdeco_file(tmp_path / "g.ply", 5, 1, False)
    raw = (tmp_path / "g.ply").read_bytes()
    cases = {
        "truncated": (raw[:-7], "truncated"),
        "ascii": (raw.replace(b"binary_little_endian", b"ascii", 1), "binary_little_endian"),
        "not a ply": (b"hello" + raw, "not a PLY"),
        "missing opacity": (raw.replace(b"property float opacity", b"property float opacitx"),
                            "missing vertex properties ['opacity']"),
        "odd f_rest": (raw.replace(b"property float f_rest_8\n", b""), "f_rest"),
        "list property": (raw.replace(b"property float nx", b"property list uchar int nx"),
                          "list property"),
    }
    assert len(data) == 5
    for name, (content, message) in cases.items():
        (tmp_path / f"{name}.ply").write_bytes(content)
        with pytest.raises(ValueError, match=re.escape(message)):
            read_ply(tmp_path / f"{name}.ply")
