"""`ctgs export --format ply|splat|glb`: each writer against an independent reading of its bytes, a read-back
round trip, and (for the geometry) renders of the read-back model against the original."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
import torch
from factory_io import random_model

from ctgs.errors import UserError
from ctgs.formats import gltf
from ctgs.formats.plain_ply import SH_C0, read_plain_ply, surfels_from_gaussians, texture_means, write_plain_ply
from ctgs.formats.splat import read_splat, write_splat
from ctgs.model.surfels import SurfelModel
from ctgs.render import render
from ctgs.render.camera import Camera

# float32 storage of float64-rendered scenes: images agree to about this (observed worst ~3e-6).
RENDER_ATOL = 2e-5
# Baking vs the float64 reference renderer at the same hit point (observed worst 4e-8: the renderer
# reaches the hit through the camera ray, the bake takes local coordinates directly). A texture read
# mirrored or off by one texel differs by ~0.1.
BAKE_ATOL = 1e-6


def _camera(width: int = 48, height: int = 40) -> Camera:
    """Looks at the random models (means ~N(0, 1)) from z = -6."""
    view = torch.eye(4, dtype=torch.float32)
    view[2, 3] = 6.0
    return Camera(fx=40.0, fy=40.0, cx=width / 2, cy=height / 2, width=width, height=height, viewmat=view)


def _untextured(n: int = 30, sh_degree: int = 3, seed: int = 3) -> SurfelModel:
    m = random_model(n=n, sh_degree=sh_degree, seed=seed)
    m.texture_mode = "none"
    m.sh_degree = sh_degree
    return m


def _image(model: SurfelModel) -> torch.Tensor:
    with torch.no_grad():
        return render(model.render_inputs(), _camera(), backend="reference", sh_degree=model.sh_degree).rgb


# ---- 3DGS PLY -------------------------------------------------------------------------------------------
def test_ply_round_trip_keeps_geometry_sh_and_folds_textures(tmp_path):
    model = random_model(n=25, sh_degree=3, seed=1)
    write_plain_ply(model, str(tmp_path / "m.ply"))
    back = read_plain_ply(str(tmp_path / "m.ply"))
    assert back.texture_mode == "none" and back.num_texels == 0 and back.sh.shape == (25, 16, 3)
    for name in ("means", "log_scales", "quats", "opacity_logits"):
        assert torch.equal(getattr(back, name), getattr(model, name).float()), name  # float32 in, float32 out
    dc = model.sh[:, 0].double() + texture_means(model) / SH_C0
    torch.testing.assert_close(back.sh[:, 0].double(), dc, rtol=1e-6, atol=1e-6)
    k = (model.sh_degree + 1) ** 2  # bands above the rendered degree are zeroed for viewers
    assert torch.equal(back.sh[:, 1:k], model.sh[:, 1:k].float()) and not back.sh[:, k:].any()


def test_ply_of_an_untextured_model_renders_identically(tmp_path):
    model = _untextured()
    write_plain_ply(model, str(tmp_path / "m.ply"))
    torch.testing.assert_close(_image(read_plain_ply(str(tmp_path / "m.ply"))), _image(model), rtol=0, atol=RENDER_ATOL)


def test_gaussians_whose_flat_axis_is_not_the_third_become_the_same_surfels():
    """A foreign 3DGS PLY may put the flat axis anywhere: axes (n, u, v) with scales (flat, su, sv) are
    the same surfel as (u, v, n) with (su, sv, flat), rendered identically."""
    model = _untextured(n=20, seed=4)
    from ctgs.render.geometry import quat_to_rotmat, rotmat_to_quat

    r = quat_to_rotmat(model.quats.double())
    cyclic = rotmat_to_quat(torch.stack([r[:, :, 2], r[:, :, 0], r[:, :, 1]], 2)).float()  # columns n, u, v
    flat = model.log_scales.min(1).values - 7.0
    g = surfels_from_gaussians(model.means, torch.cat([flat[:, None], model.log_scales], 1), cyclic,
                               model.opacity_logits, model.sh)
    torch.testing.assert_close(g.log_scales, model.log_scales.float())
    torch.testing.assert_close(_image(g), _image(model), rtol=0, atol=RENDER_ATOL)


def test_ply_reader_names_what_is_missing(tmp_path):
    from ctgs.formats.ply import write_ply

    write_ply(str(tmp_path / "x.ply"), {"x": np.zeros(2, np.float32), "y": np.zeros(2, np.float32)})
    with pytest.raises(UserError, match=r"x.ply: not a 3DGS PLY \(properties \['z', 'opacity'"):
        read_plain_ply(str(tmp_path / "x.ply"))


# ---- .splat ---------------------------------------------------------------------------------------------
def test_splat_bytes_follow_the_32_byte_layout(tmp_path):
    model = random_model(n=10, sh_degree=2, seed=2)
    assert write_splat(model, str(tmp_path / "m.splat")) == 320
    raw = (tmp_path / "m.splat").read_bytes()
    area = (model.scales[:, 0] * model.scales[:, 1] * model.opacities).double()
    first = int(torch.argmax(area))  # file order: tangent area x opacity, largest first
    x, y, z, s0, s1, s2, r, g, b, a, qw, qx, qy, qz = struct.unpack("<6f8B", raw[:32])
    assert (x, y, z) == tuple(model.means[first].tolist())
    assert s0 == pytest.approx(math.exp(model.log_scales[first, 0]), rel=1e-6)
    assert s1 == pytest.approx(math.exp(model.log_scales[first, 1]), rel=1e-6)
    assert s2 == pytest.approx(1e-3 * min(s0, s1), rel=1e-5)
    dc = model.sh[first, 0].double() + texture_means(model)[first] / SH_C0
    expect = torch.round(255 * (0.5 + SH_C0 * dc).clamp(0, 1)).tolist()
    assert [r, g, b] == expect and a == round(255 * float(model.opacities[first]))
    q = torch.nn.functional.normalize(model.quats[first].double(), dim=0)
    assert [qw, qx, qy, qz] == torch.round(128 * q + 128).clamp(0, 255).tolist()


def test_splat_round_trip_within_quantisation(tmp_path):
    model = _untextured(n=40, sh_degree=0, seed=5)
    write_splat(model, str(tmp_path / "m.splat"))
    back = read_splat(str(tmp_path / "m.splat"))
    order = torch.argsort(-(model.scales[:, 0] * model.scales[:, 1] * model.opacities).double(), stable=True)
    assert torch.equal(back.means, model.means[order])
    torch.testing.assert_close(back.log_scales, model.log_scales[order], rtol=0, atol=1e-6)
    assert (back.opacities - model.opacities[order]).abs().max() <= 0.5 / 255 + 1e-6
    colour = lambda m: 0.5 + SH_C0 * m.sh[:, 0]  # noqa: E731
    assert (colour(back) - colour(model)[order].clamp(0, 1)).abs().max() <= 0.5 / 255 + 1e-6
    q0 = torch.nn.functional.normalize(model.quats[order], dim=1)
    q1 = torch.nn.functional.normalize(back.quats, dim=1)
    assert ((q0 * q1).sum(1).abs() > math.cos(math.radians(1.5))).all()  # 8-bit components: < ~1 degree


def test_splat_reader_refuses_other_files(tmp_path):
    (tmp_path / "x.splat").write_bytes(b"\0" * 33)
    with pytest.raises(UserError, match=r"x.splat: 33 bytes is not a multiple of 32"):
        read_splat(str(tmp_path / "x.splat"))


# ---- .glb -----------------------------------------------------------------------------------------------
def _one_surfel(texture: torch.Tensor, res=(4, 3), texel=0.12) -> SurfelModel:
    """One surfel facing the camera at z = 2, scales (0.3, 0.2), a res_u x res_v texture."""
    n_tex = res[0] * res[1]
    raw = torch.logit((texture.reshape(n_tex, 3).double() + 1) / 2)  # activated = texture
    return SurfelModel(
        means=torch.tensor([[0.05, -0.03, 2.0]], dtype=torch.float64),
        log_scales=torch.log(torch.tensor([[0.3, 0.2]], dtype=torch.float64)),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64),
        opacity_logits=torch.tensor([2.5], dtype=torch.float64),
        sh=torch.tensor([[[0.2, -0.4, 0.6]]], dtype=torch.float64), textures_raw=raw,
        k_min=torch.tensor([texel], dtype=torch.float64), t2p_exp=torch.zeros(1, dtype=torch.int32),
        tex_res=torch.tensor([res], dtype=torch.int32), tex_offset=torch.zeros(1, dtype=torch.int64))


def test_baked_colour_and_alpha_are_what_the_renderer_draws():
    """A single surfel seen head-on: the reference renderer's colour (rgb / alpha) and alpha at each pixel's
    ray hit equal the baking function at that hit's local coordinates."""
    texture = (torch.rand(12, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5) * 1.6
    model = _one_surfel(texture)
    cam = Camera(fx=60.0, fy=60.0, cx=24.0, cy=20.0, width=48, height=40, viewmat=torch.eye(4, dtype=torch.float64))
    out = render(model.render_inputs(), cam, backend="reference", sh_degree=0)
    ys, xs = torch.nonzero(out.alpha > 0.05, as_tuple=True)
    assert len(ys) > 200
    # Pixel ray (x+0.5-cx)/fx, (y+0.5-cy)/fy, 1 hits the plane z = 2 at local (u, v) = hit - mean.
    lx = (xs + 0.5 - cam.cx) / cam.fx * 2.0 - 0.05
    ly = (ys + 0.5 - cam.cy) / cam.fy * 2.0 + 0.03
    baked = gltf.bake_at(model, torch.zeros(len(ys), dtype=torch.long), lx.double(), ly.double())
    alpha = out.alpha[ys, xs]
    torch.testing.assert_close(alpha, baked[:, 3], rtol=0, atol=BAKE_ATOL)
    drawn = (out.rgb[ys, xs] / alpha[:, None]).clamp(max=1.0)  # the renderer clamps colour at 0 only, PNG at 1
    torch.testing.assert_close(drawn, baked[:, :3], rtol=0, atol=BAKE_ATOL)
    assert baked[:, :3].std(0).min() > 0.05  # the texture really varies over the checked pixels


def test_glb_round_trip_quads_uvs_and_atlas(tmp_path, monkeypatch):
    # A small page limit forces several pages (and so several meshes and materials).
    monkeypatch.setattr(gltf, "ATLAS_MAX", 128)
    model = random_model(n=24, sh_degree=1, seed=6)
    size = gltf.write_glb(model, str(tmp_path / "m.glb"))
    assert size == (tmp_path / "m.glb").stat().st_size
    back = gltf.read_glb(str(tmp_path / "m.glb"))
    assert len(back.pages) > 1 and back.num_quads == 24
    assert back.material["alphaMode"] == "BLEND" and back.material["doubleSided"]
    assert gltf.UNLIT in back.material["extensions"]
    corners = gltf.quad_corners(model)  # [N, 4, 3]
    sizes = gltf.tile_sizes(model)
    seen = 0
    for page in back.pages:
        h_img, w_img = page.image.shape[:2]
        assert page.indices.max() < 4 * len(page.positions)
        for quad, uv in zip(page.positions, page.uvs):
            i = int(np.argmin(np.abs(corners - quad).reshape(len(corners), -1).max(1)))
            assert np.array_equal(corners[i], quad)  # exact float32 corners
            x0, y0 = uv[0] * (w_img, h_img)  # corner (-u, -v) = the tile's top-left pixel edge
            x1, y1 = uv[2] * (w_img, h_img)
            w, h = int(round(x1 - x0)), int(round(y1 - y0))
            assert (w, h) == tuple(sizes[i])
            tile = page.image[int(round(y0)): int(round(y0)) + h, int(round(x0)): int(round(x0)) + w]
            px, py = torch.meshgrid(torch.arange(w), torch.arange(h), indexing="xy")
            half = 3 * model.scales[i].double()
            lx = ((2 * px.reshape(-1) + 1) / w - 1) * half[0]
            ly = ((2 * py.reshape(-1) + 1) / h - 1) * half[1]
            expect = torch.round(255 * gltf.bake_at(model, torch.full_like(lx, i, dtype=torch.long), lx, ly))
            assert np.array_equal(tile.reshape(-1, 4), expect.numpy().astype(np.uint8))
            seen += 1
    assert seen == 24


def test_glb_of_an_empty_model_is_refused(tmp_path):
    empty = random_model(n=0)
    with pytest.raises(UserError, match="no surfels"):
        gltf.write_glb(empty, str(tmp_path / "e.glb"))
    assert not (tmp_path / "e.glb").exists()


def test_read_glb_refuses_other_files(tmp_path):
    (tmp_path / "x.glb").write_bytes(b"not a glb at all")
    with pytest.raises(UserError, match="x.glb: not a readable glTF binary"):
        gltf.read_glb(str(tmp_path / "x.glb"))


# ---- conversion a block of rows at a time (baked models run to millions) ---------------------------------
def test_writers_give_the_same_bytes_whatever_their_block_size(tmp_path, monkeypatch):
    import ctgs.formats.plain_ply
    import ctgs.formats.splat
    import ctgs.formats.spz

    model = random_model(n=40, sh_degree=3, seed=8)
    model.sh = model.sh.double()  # a float64 model: the blocks must copy, never write into the model
    sh = model.sh.clone()

    def outputs(rows: int) -> tuple[bytes, bytes, bytes]:
        for mod in (ctgs.formats.plain_ply, ctgs.formats.splat, ctgs.formats.spz):
            monkeypatch.setattr(mod, "PLAIN_ROWS" if mod is ctgs.formats.plain_ply else "ROWS", rows)
        write_plain_ply(model, str(tmp_path / f"m{rows}.ply"))
        write_splat(model, str(tmp_path / f"m{rows}.splat"))
        return ((tmp_path / f"m{rows}.ply").read_bytes(), (tmp_path / f"m{rows}.splat").read_bytes(),
                ctgs.formats.spz.spz_bytes(model)[0])

    one, blocks = outputs(1 << 20), outputs(7)
    assert one[0] == blocks[0] and one[2] == blocks[2]
    # .splat sorts by importance; float64 exp may round a tie's last bit differently per block: same records.
    rec = lambda b: np.sort(np.frombuffer(b, "V32"))  # noqa: E731
    assert np.array_equal(rec(one[1]), rec(blocks[1]))
    assert torch.equal(model.sh, sh)
