"""The proxy as geometry: shadow, ground and lit masks of each proxy view instead of its intensities."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from dummies import proxy_pipeline

from sar_zero123.data import DecibelScaling
from sar_zero123.domain import to_decibels
from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.conditioning import PoseProjection
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.spatial_pose import (
    GEOMETRY_BLUR_PX,
    proxy_condition_views,
    proxy_form,
    proxy_geometry,
    use_proxy_geometry,
)
from sar_zero123.sim.proxy import ProxyBank

BANK = {"num_vehicles": 6, "first_seed": 0, "blur_sigma_px": 1.5, "render_seed": 0}
PROXY = {**BANK, "max_shift_px": 0, "min_db": -60.0, "max_db": 0.0, "min_fit_score": -1.0}


def _blocks() -> torch.Tensor:
    """Ground at 0.4 with faint texture, a lit block (rows 4-13) and a shadow block (rows 18-27)."""
    view = 0.4 + 0.01 * torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    view[..., 4:14, 4:14] = 0.9
    view[..., 18:28, 4:14] = 0.1
    return view


def test_lit_shadow_and_ground_take_their_three_levels_and_nothing_else() -> None:
    masks = proxy_geometry(_blocks())
    assert masks.shape == (1, 1, 32, 32) and masks.dtype == torch.float32
    assert set(masks.unique().tolist()) == {0.0, 0.5, 1.0}
    margin = int(np.ceil(2 * GEOMETRY_BLUR_PX))  # the blur's reach into a block's edge
    lit = masks[0, 0, 4 + margin : 14 - margin, 4 + margin : 14 - margin]
    shadow = masks[0, 0, 18 + margin : 28 - margin, 4 + margin : 14 - margin]
    ground = masks[0, 0, :, 14 + 2 * margin :]
    assert (lit == 1.0).all() and (shadow == 0.0).all() and (ground == 0.5).all()


def test_the_masks_ignore_the_decibel_scaling_and_a_flat_view_is_all_ground() -> None:
    bank = ProxyBank(**BANK)
    render = torch.from_numpy(to_decibels(bank.render(2, 40.0, 17.0, 64))).float()[None, None]  # 64 px chips
    masks = proxy_geometry(render)
    assert (masks == 1.0).any() and (masks == 0.0).any() and (masks == 0.5).float().mean() > 0.5
    for scale, offset in ((1.0 / 60.0, 1.0), (2.0, -3.0)):  # normalised dB, any affine map of decibels
        same = (proxy_geometry(render * scale + offset) == masks).float().mean()
        assert float(same) >= 0.998  # a pixel on a threshold may flip with the rounding
    # an RGB copy reads as its gray view; a constant view has no geometry
    np.testing.assert_array_equal(proxy_geometry(render.expand(-1, 3, -1, -1)), masks)
    assert (proxy_geometry(torch.full((2, 1, 16, 16), 0.3)) == 0.5).all()


def test_forms_are_checked_by_name_and_old_models_read_the_render() -> None:
    views = _blocks()
    assert proxy_condition_views(views, "render") is views
    np.testing.assert_array_equal(proxy_condition_views(views, "geometry"), proxy_geometry(views))
    with pytest.raises(ValueError, match="`proxy_form` must be one of"):
        proxy_condition_views(views, "masks")
    with pytest.raises(ValueError, match="`proxy_form` must be one of"):
        PoseProjection(16, 8, proxy_form="masks")
    for bad in (torch.rand(32, 32), torch.full((1, 1, 8, 8), float("nan"))):
        with pytest.raises(ValueError, match="proxy views: expected finite"):
            proxy_geometry(bad)
    plain = build_sar_zero123("tiny", seed=0)
    assert proxy_form(plain.pose_projection) == "render"
    with pytest.raises(ValueError, match="proxy_geometry: only a spatial_pose='proxy' model"):
        use_proxy_geometry(plain.pose_projection)


def _proxy_pipeline() -> SARZero123Pipeline:
    return proxy_pipeline(PROXY)


def test_a_geometry_model_reads_the_masks_of_the_views_it_is_given_or_fits(tmp_path) -> None:
    """A geometry pipeline given (or fitting) a proxy computes what the same weights reading the render
    compute when handed that proxy's masks; it round-trips with its form."""
    pipe = _proxy_pipeline()
    size = pipe.default_image_size
    bank = ProxyBank(**BANK)
    image = torch.rand(1, 1, size, size, generator=torch.Generator().manual_seed(3))
    scaling = DecibelScaling(min_db=-60.0, max_db=0.0)
    index = int(np.argmax(bank.scores(image[0, 0].double().numpy(), 40.0, 17.0)))
    views = torch.stack([scaling.normalize(torch.from_numpy(bank.render(index, az, 17.0, size))).float()
                         for az in (40.0, 130.0)])[None]  # fmt: skip
    masks = proxy_geometry(views.reshape(2, 1, size, size)).reshape(1, 2, size, size)
    kwargs = {"num_inference_steps": 2, "guidance_scale": 1.0, "output_type": "np",
              "input_depression_deg": 17.0}  # fmt: skip
    as_render = pipe(image, 90.0, 0.0, proxy_views=masks, generator=torch.Generator().manual_seed(0),
                     **kwargs).images  # fmt: skip
    rendered = pipe(image, 90.0, 0.0, proxy_views=views, generator=torch.Generator().manual_seed(0),
                    **kwargs).images  # fmt: skip
    use_proxy_geometry(pipe.pose_projection)
    given = pipe(image, 90.0, 0.0, proxy_views=views, generator=torch.Generator().manual_seed(0),
                 **kwargs).images  # fmt: skip
    fitted = pipe(image, 90.0, 0.0, input_azimuth_deg=40.0, generator=torch.Generator().manual_seed(0),
                  **kwargs).images  # fmt: skip
    np.testing.assert_allclose(given, as_render, atol=1e-5)
    np.testing.assert_allclose(fitted, as_render, atol=1e-5)
    assert np.abs(given - rendered).max() > 1e-3  # the form changes what the UNet reads
    pipe.save_pretrained(tmp_path / "pipe")
    assert proxy_form(SARZero123Pipeline.from_pretrained(tmp_path / "pipe").pose_projection) == "geometry"
