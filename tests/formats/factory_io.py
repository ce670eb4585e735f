"""Random SurfelModels for the I/O tests (jagged textures with a gap, mixed resolutions, no-texture prims)."""

from __future__ import annotations

import torch

from ctgs.model.surfels import SurfelModel, jagged_offsets


def random_model(n: int = 40, sh_degree: int = 3, dtype=torch.float32, seed: int = 0,
                 texture_mode: str = "content_aware") -> SurfelModel:
    g = torch.Generator().manual_seed(seed)
    k = (sh_degree + 1) ** 2
    res = torch.randint(1, 9, (n, 2), generator=g, dtype=torch.int32)
    res[::7] = 0  # some primitives without texture
    offsets = jagged_offsets(res)
    t = int((res[:, 0].long() * res[:, 1].long()).sum())
    return SurfelModel(
        means=torch.randn(n, 3, generator=g, dtype=dtype),
        log_scales=torch.randn(n, 2, generator=g, dtype=dtype) * 0.3 - 2.0,
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        opacity_logits=torch.randn(n, generator=g, dtype=dtype),
        sh=torch.randn(n, k, 3, generator=g, dtype=dtype) * 0.3,
        textures_raw=torch.randn(t, 3, generator=g, dtype=dtype),
        k_min=torch.rand(n, generator=g, dtype=dtype) * 0.01 + 1e-3,
        t2p_exp=torch.randint(1, 5, (n,), generator=g, dtype=torch.int32),
        tex_res=res,
        tex_offset=offsets,
        sh_degree=min(sh_degree, 2),
        texture_mode=texture_mode,
    )


def assert_models_identical(a: SurfelModel, b: SurfelModel) -> None:
    """Bit-exact: same dtypes, same bytes (NaN-safe via bit views), same metadata."""
    for name, va in a.state_dict().items():
        vb = b.state_dict()[name]
        if isinstance(va, torch.Tensor):
            assert va.dtype == vb.dtype, name
            assert va.shape == vb.shape, name
            if va.is_floating_point():
                bits = {2: torch.int16, 4: torch.int32, 8: torch.int64}[va.element_size()]
                assert torch.equal(va.contiguous().view(bits), vb.contiguous().view(bits)), name
            else:
                assert torch.equal(va, vb), name
        else:
            assert va == vb, name
