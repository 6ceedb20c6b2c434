"""Tests for SARZero123Pipeline on the tiny dummy components (CPU, 2 denoising steps)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import PIL.Image
import pytest
import torch
from accelerate import init_empty_weights
from diffusers import (
    DiffusionPipeline,
    DPMSolverMultistepScheduler,
    EulerAncestralDiscreteScheduler,
    EulerDiscreteScheduler,
)
from dummies import DUMMY_IMAGE_SIZE, dummy_images, get_dummy_components

from sar_zero123.model.build import build_sar_zero123
from sar_zero123.model.conditioning import PoseProjection
from sar_zero123.model.pipeline import SARZero123Pipeline, SARZero123PipelineOutput
from sar_zero123.model.spatial_pose import rotate_condition_latents

STEPS = 2


@pytest.fixture(scope="module")
def pipe() -> SARZero123Pipeline:
    pipeline = SARZero123Pipeline(**get_dummy_components())
    pipeline.set_progress_bar_config(disable=True)
    return pipeline


def run(pipe, image=None, seed=0, **kwargs) -> torch.Tensor:
    image = dummy_images() if image is None else image
    kwargs = {"d_az": 30.0, "d_el": 0.0, "num_inference_steps": STEPS, "output_type": "pt", **kwargs}
    if "generator" not in kwargs:
        kwargs["generator"] = torch.Generator().manual_seed(seed)
    return pipe(image, **kwargs).images


# ---------------------------------------------------------------------------------- outputs
def test_seeded_output_slice(pipe):
    images = run(pipe, output_type="np")
    assert images.shape == (1, DUMMY_IMAGE_SIZE, DUMMY_IMAGE_SIZE, 1)
    # Recorded on CPU (torch 2.13, diffusers 0.42) from the dummy components; tolerance 1e-3 absorbs
    # BLAS/threading differences between CPUs.
    expected = np.array([0.4396, 0.4938, 0.4830, 0.3915, 0.4782, 0.4828, 0.3871, 0.4195, 0.4890])
    np.testing.assert_allclose(images[0, -3:, -3:, 0].flatten(), expected, atol=1e-3)


@pytest.mark.parametrize("output_type", ["np", "pt", "pil", "latent"])
def test_output_shapes_for_batch_and_images_per_prompt(pipe, output_type):
    output = pipe(
        dummy_images(batch_size=2),
        d_az=[30.0, 60.0],
        d_el=0.0,
        num_inference_steps=1,
        num_images_per_prompt=3,
        generator=torch.Generator().manual_seed(0),
        output_type=output_type,
    )
    assert isinstance(output, SARZero123PipelineOutput)
    images = output.images
    if output_type == "np":
        assert images.shape == (6, 32, 32, 1) and images.dtype == np.float32
        assert images.min() >= 0.0 and images.max() <= 1.0
    elif output_type == "pt":
        assert images.shape == (6, 1, 32, 32)
    elif output_type == "pil":
        assert len(images) == 6 and all(im.mode == "L" and im.size == (32, 32) for im in images)
    else:
        assert images.shape == (6, 4, 16, 16)


def test_return_dict_false_gives_a_tuple(pipe):
    output = pipe(dummy_images(), d_az=10.0, num_inference_steps=1, output_type="pt", return_dict=False)
    assert isinstance(output, tuple) and output[0].shape == (1, 1, 32, 32)


def test_same_seed_same_output_and_other_seed_differs(pipe):
    first, second, other = run(pipe, seed=1), run(pipe, seed=1), run(pipe, seed=2)
    assert torch.equal(first, second)
    assert (first - other).abs().max() > 1e-3


def test_list_of_generators_matches_single_runs(pipe):
    images = dummy_images(batch_size=2)
    generators = [torch.Generator().manual_seed(5), torch.Generator().manual_seed(7)]
    batched = run(pipe, images, d_az=[30.0, 90.0], generator=generators)
    single_0 = run(pipe, images[:1], d_az=30.0, seed=5)
    single_1 = run(pipe, images[1:], d_az=90.0, seed=7)
    torch.testing.assert_close(batched, torch.cat([single_0, single_1]), atol=1e-4, rtol=0)


def test_images_per_prompt_samples_differ(pipe):
    images = run(pipe, num_images_per_prompt=2)
    assert (images[0] - images[1]).abs().max() > 1e-3


def test_azimuth_periodicity(pipe):
    assert torch.equal(run(pipe, d_az=10.0), run(pipe, d_az=370.0))
    assert torch.equal(run(pipe, d_az=10.0), run(pipe, d_az=-350.0))


def test_pose_changes_the_output_once_the_projection_uses_it():
    pipe = SARZero123Pipeline(**get_dummy_components())
    pipe.set_progress_bar_config(disable=True)
    # At initialisation the pose part of the projection is zero (REFERENCE.md): the pose cannot matter.
    assert torch.equal(run(pipe, d_az=10.0), run(pipe, d_az=100.0))
    with torch.no_grad():
        pipe.pose_projection.projection.weight[:, -4:].normal_(generator=torch.Generator().manual_seed(0))
    assert (run(pipe, d_az=10.0) - run(pipe, d_az=100.0)).abs().max() > 1e-4


@pytest.mark.parametrize(
    "scheduler_class", [DPMSolverMultistepScheduler, EulerDiscreteScheduler, EulerAncestralDiscreteScheduler]
)
def test_scheduler_swap(scheduler_class):
    pipe = SARZero123Pipeline(**get_dummy_components())
    pipe.set_progress_bar_config(disable=True)
    ddim = run(pipe, num_inference_steps=3)
    pipe.scheduler = scheduler_class.from_config(pipe.scheduler.config)
    swapped, again = run(pipe, num_inference_steps=3), run(pipe, num_inference_steps=3)
    assert swapped.shape == ddim.shape and torch.isfinite(swapped).all()
    assert torch.equal(swapped, again)  # stochastic samplers too take the pipeline's generator
    assert (swapped - ddim).abs().max() > 1e-4


def _record_unet_calls(pipe):
    calls = []

    def hook(module, args, kwargs):
        calls.append((args[0].clone(), kwargs["encoder_hidden_states"].clone()))

    return calls, pipe.unet.register_forward_pre_hook(hook, with_kwargs=True)


@pytest.mark.parametrize(("guidance_scale", "factor"), [(3.0, 2), (1.0, 1), (0.5, 1)])
def test_guidance_batches_unconditional_zeros_in_one_call(pipe, guidance_scale, factor):
    calls, handle = _record_unet_calls(pipe)
    try:
        run(pipe, dummy_images(batch_size=2), d_az=[0.0, 45.0], guidance_scale=guidance_scale)
    finally:
        handle.remove()
    assert len(calls) == STEPS  # one UNet call per step
    for model_input, tokens in calls:
        assert model_input.shape == (2 * factor, 8, 16, 16)
        assert tokens.shape == (2 * factor, 1, 16)
        if factor == 2:
            # unconditional half first: zero token and zero condition latent; the noisy latents are shared
            assert torch.count_nonzero(tokens[:2]) == 0 and torch.count_nonzero(model_input[:2, 4:]) == 0
            assert torch.count_nonzero(tokens[2:]) > 0 and torch.count_nonzero(model_input[2:, 4:]) > 0
            assert torch.equal(model_input[:2, :4], model_input[2:, :4])


def _naive_guided_ddim(pipe, x, images, pose, steps, first_index, scale):
    """LDM DDIM (eta 0) with zero-1-to-3's batched CFG, written out step by step from timestep index
    ``first_index`` down to 0 of the ``steps``-step schedule (timesteps 1, 1 + 1000 / steps, ...), then
    decoded to [0, 1]."""
    betas = torch.linspace(0.00085**0.5, 0.012**0.5, 1000, dtype=torch.float64) ** 2  # scaled_linear
    alphas_cumprod = torch.cumprod(1 - betas, 0)
    timesteps = torch.arange(0, 1000, 1000 // steps) + 1
    with torch.no_grad():
        tokens, condition = pipe.encode_conditioning(images, pose)
        tokens = torch.cat([torch.zeros_like(tokens), tokens])
        condition = torch.cat([torch.zeros_like(condition), condition])
        for index in reversed(range(first_index + 1)):
            a_t = alphas_cumprod[timesteps[index]].item()
            a_prev = alphas_cumprod[timesteps[index - 1] if index > 0 else 0].item()
            model_input = torch.cat([torch.cat([x, x]), condition], dim=1)
            eps_uncond, eps_cond = pipe.unet(model_input, timesteps[index], tokens).sample.chunk(2)
            eps = eps_uncond + scale * (eps_cond - eps_uncond)
            x0 = (x - (1 - a_t) ** 0.5 * eps) / a_t**0.5
            x = a_prev**0.5 * x0 + (1 - a_prev) ** 0.5 * eps
        return (pipe.vae.decode(x / pipe.vae.config.scaling_factor).sample / 2 + 0.5).clamp(0, 1)


def test_ddim_guided_sampling_matches_the_original_zero123_equations(pipe):
    """Naive reference: LDM DDIM (eta 0) with zero-1-to-3's batched CFG, written out step by step."""
    steps, scale = 5, 3.0
    images = dummy_images(batch_size=2)
    noise = torch.randn(2, 4, 16, 16, generator=torch.Generator().manual_seed(9))
    output = run(
        pipe,
        images,
        d_az=[30.0, 120.0],
        d_el=[0.0, 4.0],
        latents=noise,
        generator=None,
        num_inference_steps=steps,
        guidance_scale=scale,
    )
    pose = torch.tensor([[[0.0, 0.5, 3**0.5 / 2, 0.0]], [[4 * torch.pi / 180, 3**0.5 / 2, -0.5, 0.0]]])
    expected = _naive_guided_ddim(pipe, noise, images, pose, steps, steps - 1, scale)  # 801, 601, ..., 1
    torch.testing.assert_close(output, expected, atol=1e-5, rtol=0)


@pytest.mark.parametrize("start_from", ["input", "turned_input"])
def test_strength_runs_the_last_steps_from_the_noised_input_latent(pipe, start_from):
    """Naive reference: SDEdit on LDM DDIM (eta 0): the input's latent (posterior mode x scaling factor),
    with "turned_input" turned in the image plane by the requested d_az first, noised to the
    int(steps * strength)-th last timestep, then only those steps."""
    steps, strength, scale = 5, 0.6, 3.0
    images = dummy_images(batch_size=2)
    noise = torch.randn(2, 4, 16, 16, generator=torch.Generator().manual_seed(9))
    calls, handle = _record_unet_calls(pipe)
    try:
        output = run(pipe, images, d_az=[30.0, 120.0], latents=noise, generator=None,
                     num_inference_steps=steps, guidance_scale=scale, strength=strength,
                     start_from=start_from)  # fmt: skip
    finally:
        handle.remove()
    assert len(calls) == 3  # int(5 * 0.6)
    pose = torch.tensor([[[0.0, 0.5, 3**0.5 / 2, 0.0]], [[0.0, 3**0.5 / 2, -0.5, 0.0]]])
    betas = torch.linspace(0.00085**0.5, 0.012**0.5, 1000, dtype=torch.float64) ** 2  # scaled_linear
    a_start = torch.cumprod(1 - betas, 0)[401].item()  # timesteps 1, 201, 401, 601, 801: start at 401
    with torch.no_grad():
        start = pipe.encode_conditioning(images, pose)[1]
    if start_from == "turned_input":
        start = rotate_condition_latents(start, pose, pipe.pose_projection.config.rotation_sign)
    start = start * pipe.vae.config.scaling_factor
    x = a_start**0.5 * start + (1 - a_start) ** 0.5 * noise
    expected = _naive_guided_ddim(pipe, x, images, pose, steps, 2, scale)
    torch.testing.assert_close(output, expected, atol=1e-5, rtol=0)


def test_strength_one_is_sampling_from_noise_and_a_small_strength_keeps_the_input(pipe):
    assert torch.equal(run(pipe, num_inference_steps=10, strength=1.0), run(pipe, num_inference_steps=10))
    with torch.no_grad():
        start = pipe.encode_conditioning(dummy_images(), torch.zeros(1, 1, 4))[1]
    start = start * pipe.vae.config.scaling_factor
    kept = run(pipe, num_inference_steps=10, strength=0.1, output_type="latent")  # one step from t = 1
    full = run(pipe, num_inference_steps=10, output_type="latent")
    assert (kept - start).abs().mean() < 0.05 * (full - start).abs().mean()


@pytest.mark.parametrize(
    ("strength", "match"),
    [(0.0, r"\(0, 1\], got 0.0"), (1.5, r"\(0, 1\], got 1.5"), (float("nan"), "got nan"), (True, "got True"),
     (0.2, r"^strength 0.2 x num_inference_steps 2 leaves no denoising step")],
)  # fmt: skip
def test_bad_strength_is_refused(pipe, strength, match):
    with pytest.raises(ValueError, match=match):
        run(pipe, strength=strength)


def test_a_turned_start_at_no_turn_is_the_input_start_and_a_bad_start_is_refused(pipe):
    kwargs = {"d_az": 0.0, "num_inference_steps": 4, "strength": 0.5, "output_type": "latent"}
    torch.testing.assert_close(run(pipe, start_from="turned_input", **kwargs), run(pipe, **kwargs))
    with pytest.raises(ValueError, match=r"`start_from` must be one of .*, got 'noise'"):
        run(pipe, start_from="noise")


def test_guidance_changes_the_output(pipe):
    assert (run(pipe, guidance_scale=3.0) - run(pipe, guidance_scale=1.0)).abs().max() > 1e-4


def test_callback_on_step_end_sees_and_replaces_latents(pipe):
    seen = []

    def callback(pipeline, step, timestep, callback_kwargs):
        seen.append((step, int(timestep), callback_kwargs["latents"].shape))
        return {"latents": torch.zeros_like(callback_kwargs["latents"])}

    latents = run(pipe, output_type="latent", callback_on_step_end=callback)
    assert [s[0] for s in seen] == list(range(STEPS))
    assert all(shape == (1, 4, 16, 16) for _, _, shape in seen)
    assert torch.count_nonzero(latents) == 0


def test_given_latents_replace_the_generator(pipe):
    noise = torch.randn(1, 4, 16, 16, generator=torch.Generator().manual_seed(0))
    assert torch.equal(run(pipe, latents=noise, generator=None), run(pipe, seed=0))


def test_bf16_on_cpu():
    pipe = SARZero123Pipeline(**get_dummy_components())
    pipe.set_progress_bar_config(disable=True)
    reference = run(pipe)
    pipe.to(torch.bfloat16)
    images = run(pipe)
    assert images.dtype == torch.float32 and torch.isfinite(images).all()
    assert (images - reference).abs().max() < 0.1


def test_pil_numpy_and_rgb_inputs_match_tensor_input(pipe):
    gray_u8 = (dummy_images()[0, 0].numpy() * 255).round().astype(np.uint8)
    tensor = torch.from_numpy(gray_u8.astype(np.float32) / 255.0)[None, None]
    reference = run(pipe, tensor)
    assert torch.equal(run(pipe, PIL.Image.fromarray(gray_u8, mode="L")), reference)
    assert torch.equal(run(pipe, [gray_u8.astype(np.float32) / 255.0]), reference)
    assert torch.equal(run(pipe, gray_u8[:, :, None]), reference)
    rgb = run(pipe, PIL.Image.fromarray(np.repeat(gray_u8[:, :, None], 3, axis=2), mode="RGB"))
    torch.testing.assert_close(rgb, reference, atol=1e-4, rtol=0)


# --------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"image": torch.full((1, 1, 32, 32), float("nan"))}, "`image` contains NaN"),
        ({"image": torch.full((1, 1, 32, 32), 1.5)}, r"`image` must lie in \[0, 1\]"),
        ({"image": -torch.ones(1, 1, 32, 32)}, r"`image` must lie in \[0, 1\]"),
        ({"image": torch.rand(1, 32, 32)}, "`image` tensors must be"),
        ({"image": torch.rand(1, 2, 32, 32)}, "`image` must have 1 or 3 channels"),
        ({"image": torch.rand(0, 1, 32, 32)}, "`image` is an empty batch"),
        ({"image": torch.empty(1, 1, 32, 32, device="meta")}, "`image` is a tensor on the meta device"),
        ({"image": torch.rand(1, 1, 32, 32, dtype=torch.complex64)}, "`image` must be real"),
        ({"image": []}, "`image` is an empty list"),
        ({"image": np.zeros((2, 32, 32, 1, 1), np.float32)}, "`image` arrays must be"),
        ({"image": torch.rand(1, 1, 30, 30)}, "`image` height and width must be positive multiples of 4"),
        ({"image": "chip.png"}, "`image` must be a PIL image"),
        ({"d_az": float("nan")}, "`d_az` must be finite"),
        ({"d_el": float("inf")}, "`d_el` must be finite"),
        ({"d_az": [10.0, 20.0, 30.0]}, "`d_az` has 3 values"),
        ({"num_inference_steps": 0}, "`num_inference_steps`"),
        ({"num_images_per_prompt": 0}, "`num_images_per_prompt`"),
        ({"guidance_scale": float("nan")}, "`guidance_scale`"),
        ({"output_type": "jpg"}, "`output_type`"),
        ({"generator": [torch.Generator()] * 3}, "`generator` is a list of 3"),
        ({"latents": torch.zeros(1, 4, 8, 8)}, "`latents` must have shape"),
    ],
)
def test_invalid_inputs_raise_value_errors_naming_the_argument(pipe, kwargs, match):
    arguments = {"image": dummy_images(batch_size=2), "d_az": 30.0, "d_el": 0.0, "num_inference_steps": 1}
    arguments.update(kwargs)
    image = arguments.pop("image")
    with pytest.raises(ValueError, match=match):
        pipe(image, **arguments)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"d_az": "30"}, ValueError, r"`d_az` must be a real number of degrees .*got str '30'"),
        ({"d_az": None}, ValueError, r"`d_az` must be a real number of degrees .*got NoneType None"),
        ({"d_az": 30 + 1j}, ValueError, r"`d_az` must be a real number of degrees .*got complex"),
        ({"d_az": [10.0, "20"]}, ValueError, r"`d_az` must be a real number .*got str '20'"),
        ({"d_el": True}, ValueError, r"`d_el` must be a real number .*got bool"),
        ({"d_az": torch.tensor([1j, 2j])}, ValueError, r"`d_az` must hold real angles .*complex"),
        ({"guidance_scale": "3"}, ValueError, r"`guidance_scale` must be a real number, got str '3'"),
        ({"guidance_scale": 1e30}, ValueError, r"`guidance_scale` must be <= 100"),
        ({"d_el": 400.0}, ValueError, r"`d_el` must lie in \(-90, 90\) degrees .*got 400"),
        ({"d_el": [0.0, -91.0]}, ValueError, r"`d_el` must lie in \(-90, 90\) degrees .*got 91"),
        ({"d_el": 90.0}, ValueError, r"`d_el` must lie in \(-90, 90\) degrees .*got 90$"),
        ({"d_el": [0.0, -90.0]}, ValueError, r"`d_el` must lie in \(-90, 90\) degrees .*got 90$"),
        ({"d_az": 1e300}, ValueError, r"`d_az` must lie in \[-1e\+06, 1e\+06\] degrees .*got 1e\+300"),
    ],
    ids=["str", "None", "complex", "str-in-list", "bool", "complex-tensor", "guidance-str", "guidance-huge",
         "d_el-400", "d_el-91", "d_el-90", "d_el--90", "d_az-1e300"],
)  # fmt: skip
def test_wrong_types_and_impossible_poses_are_refused(pipe, kwargs, error, match):
    arguments = {"d_az": 30.0, "d_el": 0.0, "num_inference_steps": 1, **kwargs}
    with pytest.raises(error, match=match):
        pipe(dummy_images(batch_size=2), **arguments)


def test_non_finite_output_is_refused_naming_the_component():
    components = get_dummy_components()
    with torch.no_grad():
        next(components["unet"].parameters()).fill_(float("nan"))
    broken = SARZero123Pipeline(**components)
    broken.set_progress_bar_config(disable=True)
    with pytest.raises(FloatingPointError, match=r"non-finite latents for 2 of 2 samples; .*\['unet'\]"):
        broken(dummy_images(batch_size=2), d_az=30.0, num_inference_steps=1, output_type="np")


def test_mismatched_components_are_rejected():
    components = get_dummy_components()
    components["pose_projection"] = type(components["pose_projection"])(in_features=10, out_features=16)
    with pytest.raises(ValueError, match="pose_projection.config.in_features"):
        SARZero123Pipeline(**components)


def test_a_pipeline_folder_loads_only_as_it_was_saved(pipe, tmp_path, caplog):
    """save_pretrained seals the folder with manifest.json (size and SHA-256 of every file); from_pretrained
    refuses a changed, truncated or missing weight or config by name, loads it with verify_manifest=False
    (warning), names a file added since in a warning, and loads an older folder without a manifest with a
    warning."""
    import json

    from sar_zero123.runs.manifest import MANIFEST_FILE, file_sha256

    pipe.save_pretrained(tmp_path / "ok")
    listed = json.loads((tmp_path / "ok" / MANIFEST_FILE).read_text())["files"]
    on_disk = sorted(p.relative_to(tmp_path / "ok").as_posix() for p in (tmp_path / "ok").rglob("*")
                     if p.is_file() and p.name != MANIFEST_FILE)  # fmt: skip
    assert sorted(listed) == on_disk and "unet/diffusion_pytorch_model.safetensors" in listed
    for name, entry in listed.items():
        assert entry == {"bytes": (tmp_path / "ok" / name).stat().st_size,
                         "sha256": file_sha256(tmp_path / "ok" / name)}  # fmt: skip
    weights = "unet/diffusion_pytorch_model.safetensors"

    def changed(name, edit):
        folder = tmp_path / name
        shutil.copytree(tmp_path / "ok", folder)
        edit(folder)
        return folder

    def zero_half(folder):  # the same size, other bytes: half the UNet's weights zeroed
        data = bytearray((folder / weights).read_bytes())
        data[len(data) // 2 :] = bytes(len(data) - len(data) // 2)
        (folder / weights).write_bytes(bytes(data))

    def edit_scheduler(folder):
        config = json.loads((folder / "scheduler/scheduler_config.json").read_text())
        (folder / "scheduler/scheduler_config.json").write_text(json.dumps({**config, "beta_end": 10.0}))

    cases = {
        "zeroed": (zero_half, rf"/{weights}' does not match its SHA-256 in manifest.json \(changed"),
        "scheduler": (edit_scheduler, r"scheduler_config.json' has \d+ bytes, manifest.json records"),
        "missing": (lambda f: (f / weights).unlink(), rf"/{weights}', listed in manifest.json, is missing"),
    }  # fmt: skip
    for name, (edit, words) in cases.items():
        folder = changed(name, edit)
        with pytest.raises(ValueError, match=rf"pipeline '.*{name}': .*{words}.*verify_manifest=False"):
            SARZero123Pipeline.from_pretrained(folder)
    caplog.set_level("WARNING", logger="sar_zero123.model.pipeline_loading")
    loaded = SARZero123Pipeline.from_pretrained(tmp_path / "zeroed", verify_manifest=False)
    assert "loaded with verify_manifest=False although" in caplog.text
    assert loaded.unet.conv_in.weight.shape == pipe.unet.conv_in.weight.shape
    caplog.clear()
    (tmp_path / "zeroed" / MANIFEST_FILE).unlink()  # a folder saved before manifests: loads, with a warning
    SARZero123Pipeline.from_pretrained(tmp_path / "zeroed")
    assert f"has no {MANIFEST_FILE} (saved before manifests)" in caplog.text
    caplog.clear()
    (tmp_path / "ok" / "notes.md").write_text("a user's notes")  # not a file loading reads: not named
    SARZero123Pipeline.from_pretrained(tmp_path / "ok")
    assert caplog.text == ""
    (tmp_path / "ok" / "decibel_scaling.json").write_text("{}")  # added after saving: loads, named
    SARZero123Pipeline.from_pretrained(tmp_path / "ok")
    assert "['decibel_scaling.json'] not in its manifest.json (added after it was saved)" in caplog.text


def test_a_vae_or_unet_from_another_model_is_refused_at_load(pipe, tmp_path):
    """A VAE copied into a pipeline folder from another model: refused naming both sizes (issue 39)."""
    from diffusers import AutoencoderKL, UNet2DConditionModel

    pipe.save_pretrained(tmp_path / "ok")
    vae = pipe.vae.config
    bigger = AutoencoderKL(**{**dict(vae), "sample_size": 64})  # same nets, built for 64 px chips
    shutil.copytree(tmp_path / "ok", tmp_path / "swapped")
    shutil.rmtree(tmp_path / "swapped" / "vae")
    bigger.save_pretrained(tmp_path / "swapped" / "vae")
    with pytest.raises(ValueError, match=r"swapped/vae/config.json' does not match its SHA-256 in manifest"):
        SARZero123Pipeline.from_pretrained(tmp_path / "swapped")  # first: not the files it was saved with
    with pytest.raises(ValueError, match=r"vae: built for 64 px chips .* 16x16 latents, i.e. 32 px"):
        SARZero123Pipeline.from_pretrained(tmp_path / "swapped", verify_manifest=False)
    deeper = AutoencoderKL(**{**dict(vae), "block_out_channels": (*vae.block_out_channels, 32),
                              "down_block_types": (*vae.down_block_types, "DownEncoderBlock2D"),
                              "up_block_types": (*vae.up_block_types, "UpDecoderBlock2D")})  # fmt: skip
    with pytest.raises(ValueError, match="downsampling factor 4"):
        SARZero123Pipeline(**{**get_dummy_components(), "vae": deeper})
    components = get_dummy_components()
    unet = components["unet"]
    components["unet"] = UNet2DConditionModel(**{**dict(unet.config), "out_channels": 3})
    with pytest.raises(ValueError, match="out_channels` must be the vae's 4 latent channels, got 3"):
        SARZero123Pipeline(**components)
    SARZero123Pipeline.from_pretrained(tmp_path / "ok")  # the untouched folder still loads


def test_a_vae_of_another_shape_than_the_one_trained_with_is_refused_even_when_sizes_agree(pipe, tmp_path):
    """The issue-39 case: another model's VAE that downsamples by 4 at 64 px gives the same 16x16 latents
    as the 32 px VAE the UNet was trained with; the recorded training VAE refuses it (and names it)."""
    from diffusers import AutoencoderKL

    from sar_zero123.model.conditioning import vae_signature

    trained = dict(pipe.vae.config)
    pipe.pose_projection.register_to_config(trained_vae=vae_signature(pipe.vae.config))
    pipe.save_pretrained(tmp_path / "ok")
    other = AutoencoderKL(**{**trained, "sample_size": 64, "scaling_factor": 0.5,
                             "block_out_channels": (*trained["block_out_channels"], 32),
                             "down_block_types": (*trained["down_block_types"], "DownEncoderBlock2D"),
                             "up_block_types": (*trained["up_block_types"], "UpDecoderBlock2D")})  # fmt: skip
    shutil.copytree(tmp_path / "ok", tmp_path / "swapped")
    shutil.rmtree(tmp_path / "swapped" / "vae")
    other.save_pretrained(tmp_path / "swapped" / "vae")
    with pytest.raises(ValueError, match=r"^vae: sample_size 64 \(the model was trained with 32\); "
                                         r"block_out_channels \[16, 32, 32\] \(the model was trained with "
                                         r"\[16, 32\]\); scaling_factor 0.5 \(the model was trained with "
                                         r"0.18215\): the vae comes from another model"):  # fmt: skip
        SARZero123Pipeline.from_pretrained(tmp_path / "swapped", verify_manifest=False)
    loaded = SARZero123Pipeline.from_pretrained(tmp_path / "ok")
    assert loaded.pose_projection.config.trained_vae == vae_signature(pipe.vae.config)
    pipe.pose_projection.register_to_config(trained_vae=None)  # the module-scoped fixture as it was


# ------------------------------------------------------------------------------ save / load
def test_save_pretrained_from_pretrained_round_trip(pipe, tmp_path):
    reference = run(pipe)
    pipe.save_pretrained(tmp_path)
    model_index = json.loads((tmp_path / "model_index.json").read_text())
    assert model_index["_class_name"] == "SARZero123Pipeline"
    assert model_index["pose_projection"] == ["sar_zero123.model.conditioning", "PoseProjection"]
    loaded = SARZero123Pipeline.from_pretrained(tmp_path)
    loaded.set_progress_bar_config(disable=True)
    assert loaded.feature_extractor is None
    assert torch.equal(run(loaded), reference)
    generic = DiffusionPipeline.from_pretrained(tmp_path)  # no class named, no trust_remote_code
    assert type(generic) is SARZero123Pipeline
    generic.set_progress_bar_config(disable=True)
    assert torch.equal(run(generic), reference)


def test_a_folder_naming_a_removed_module_is_refused_naming_its_replacement(pipe, tmp_path):
    pipe.save_pretrained(tmp_path)
    index_path = tmp_path / "model_index.json"
    model_index = json.loads(index_path.read_text())
    model_index["pose_projection"] = ["sar_zero123.conditioning", "PoseProjection"]
    index_path.write_text(json.dumps(model_index))
    (tmp_path / "manifest.json").unlink()  # folders of that time had none
    with pytest.raises(
        ValueError,
        match=r"'pose_projection' is listed as sar_zero123.conditioning.PoseProjection, "
        r"a module that was removed; write \"sar_zero123.model.conditioning\" in its place",
    ):
        SARZero123Pipeline.from_pretrained(tmp_path)
    model_index["pose_projection"] = ["sar_zero123.model.conditioning", "PoseProjection"]
    index_path.write_text(json.dumps(model_index))
    assert type(SARZero123Pipeline.from_pretrained(tmp_path).pose_projection) is PoseProjection


# ---------------------------------------------------------------------------------- factory
def test_build_tiny_is_seeded_and_well_under_a_million_parameters():
    state = torch.random.get_rng_state()
    pipe = build_sar_zero123("tiny", seed=0)
    assert torch.equal(torch.random.get_rng_state(), state)  # global RNG untouched
    modules = [pipe.unet, pipe.vae, pipe.image_encoder, pipe.pose_projection]
    assert sum(p.numel() for m in modules for p in m.parameters()) == 393_385
    again = build_sar_zero123("tiny", seed=0)
    assert all(torch.equal(a, b) for a, b in zip(pipe.unet.parameters(), again.unet.parameters()))
    assert pipe.default_image_size == 32 and pipe.vae.config.in_channels == 1


def test_build_image_size_override_and_validation():
    pipe = build_sar_zero123("tiny", image_size=48)
    pipe.set_progress_bar_config(disable=True)
    assert pipe.default_image_size == 48
    assert run(pipe, torch.rand(1, 1, 48, 48), num_inference_steps=1).shape == (1, 1, 48, 48)
    with pytest.raises(ValueError, match="image_size"):
        build_sar_zero123("tiny", image_size=30)
    with pytest.raises(ValueError, match="size"):
        build_sar_zero123("huge")


def test_build_zero123_has_the_objaverse_shapes():
    with init_empty_weights():
        pipe = build_sar_zero123("zero123")
    unet = pipe.unet.config
    assert unet.in_channels == 8 and unet.out_channels == 4 and unet.sample_size == 32
    assert tuple(unet.block_out_channels) == (320, 640, 1280, 1280) and unet.layers_per_block == 2
    assert unet.cross_attention_dim == 768 and unet.attention_head_dim == 8
    assert pipe.vae.config.scaling_factor == 0.18215 and pipe.vae.config.in_channels == 3
    assert pipe.vae_scale_factor == 8 and pipe.default_image_size == 256
    assert pipe.image_encoder.config.projection_dim == 768 and pipe.image_encoder.config.image_size == 224
    assert (pipe.pose_projection.config.in_features, pipe.pose_projection.config.out_features) == (772, 768)
    # SD 1.x UNet (859,520,964 parameters) with 4 extra input channels in conv_in (4 * 320 * 3 * 3).
    assert sum(p.numel() for p in pipe.unet.parameters()) == 859_520_964 + 4 * 320 * 9
    assert pipe.scheduler.config.beta_schedule == "scaled_linear" and pipe.scheduler.config.beta_end == 0.012


def test_unet_dtype_is_read_once_per_call(pipe, monkeypatch) -> None:
    # ModelMixin.dtype walks every UNet parameter: 0.4 ms (tiny) to 1.1 ms (small) per read on this CPU.
    unet_class = type(pipe.unet)
    original = unet_class.dtype
    reads = []

    def counting(module):
        if module is pipe.unet:
            reads.append(1)
        return original.fget(module)

    monkeypatch.setattr(unet_class, "dtype", property(counting))
    run(pipe, num_inference_steps=6)
    assert len(reads) == 1


def test_a_start_image_equal_to_the_input_is_the_input_start_and_another_one_changes_the_view(pipe):
    """``start_image`` is encoded as the input is (posterior mode): the input itself as the draft gives the
    input start's bytes; another draft gives another view; a draft of another size is refused."""
    images = dummy_images(batch_size=2, seed=1)
    kwargs = {"d_az": [30.0, 150.0], "num_inference_steps": 4, "strength": 0.5, "output_type": "latent"}
    from_input = run(pipe, images, **kwargs)
    torch.testing.assert_close(run(pipe, images, start_image=images, **kwargs), from_input)
    other = run(pipe, images, start_image=images.flip(-1), **kwargs)
    assert (other - from_input).abs().max() > 1e-3
    # ignored at strength 1, as start_from is
    full = {**kwargs, "strength": 1.0}
    ignored = run(pipe, images, start_image=images.flip(-1), **full)
    torch.testing.assert_close(ignored, run(pipe, images, **full))
    with pytest.raises(ValueError, match=r"`start_image` must be one draft per input image"):
        run(pipe, images, start_image=images[:1], **kwargs)


# ------------------------------------------------------------- recorded sampler and the simulator proxy
SMALL_PROXY = {"num_vehicles": 3, "first_seed": 1_000_000, "blur_sigma_px": 1.5, "render_seed": 0,
               "max_shift_px": 0, "min_db": -60.0, "max_db": 0.0,
               "min_fit_score": -1.0}  # noise chips, which no vehicle fits  # fmt: skip


def test_a_recorded_sampler_is_the_plain_calls_and_an_argument_overrides_it(tmp_path):
    sampler = {"num_inference_steps": 3, "guidance_scale": 2.0, "strength": 0.7,
               "heading_guidance_scale": 0.5}  # fmt: skip
    recorded = SARZero123Pipeline(**get_dummy_components(), sampler=sampler)
    recorded.set_progress_bar_config(disable=True)
    plain = SARZero123Pipeline(**get_dummy_components())
    plain.set_progress_bar_config(disable=True)
    explicit = {key: sampler[key] for key in sampler}
    assert torch.equal(run(recorded, num_inference_steps=None), run(plain, **explicit))
    overridden = run(recorded, num_inference_steps=None, strength=1.0)
    assert torch.equal(overridden, run(plain, **{**explicit, "strength": 1.0}))
    # the plain pipeline's call is the library's defaults; the record survives save and load
    library = run(plain, num_inference_steps=50, guidance_scale=3.0)
    assert torch.equal(run(plain, num_inference_steps=None), library)
    recorded.save_pretrained(tmp_path)
    assert json.loads((tmp_path / "model_index.json").read_text())["sampler"] == sampler
    loaded = SARZero123Pipeline.from_pretrained(tmp_path)
    loaded.set_progress_bar_config(disable=True)
    assert loaded.config.sampler == sampler and loaded.config.proxy is None
    assert torch.equal(run(loaded, num_inference_steps=None), run(plain, **explicit))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"sampler": {"steps": 3}}, r"`sampler` must be a dict of some of"),
     ({"sampler": {"start_from": "noise"}}, r"`sampler.start_from` must be one of"),
     ({"sampler": {"start_from": "proxy"}}, r"records no `proxy` settings"),
     ({"sampler": {"proxy_strength": 1.5}}, r"sampler.proxy_strength must lie in \(0, 1\]"),
     ({"sampler": {"guidance_scale": 1e9}}, r"`sampler` \(recorded in model_index.json\): guidance"),
     ({"sampler": {"num_inference_steps": 10**7}}, r"`sampler` .*: num_inference_steps must be an"),
     ({"proxy": {**SMALL_PROXY, "num_vehicles": 0}}, r"proxy.num_vehicles: expected an integer"),
     ({"proxy": {**SMALL_PROXY, "min_db": 1.0}}, r"proxy.min_db, proxy.max_db: expected finite decibels"),
     ({"proxy": {"num_vehicles": 3}}, r"proxy: expected the fields .* missing \['blur_sigma_px'")],
)  # fmt: skip
def test_bad_recorded_settings_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SARZero123Pipeline(**get_dummy_components(), **kwargs)


def test_the_proxy_start_is_the_simulator_draft_at_the_requested_pose(tmp_path):
    from sar_zero123.model.proxy import draft_target_views

    pipe = SARZero123Pipeline(**get_dummy_components(), proxy=SMALL_PROXY)
    pipe.set_progress_bar_config(disable=True)
    images = dummy_images(batch_size=2, seed=3)
    kwargs = {"d_az": [90.0, -150.0], "num_inference_steps": 4, "strength": 0.5, "output_type": "latent"}
    drafts, fitted = draft_target_views(
        images, torch.tensor([10.0, 200.0]), torch.tensor([17.0, 17.0]), torch.tensor([90.0, -150.0]),
        torch.zeros(2), SMALL_PROXY,
    )  # fmt: skip
    assert drafts.shape == (2, 1, DUMMY_IMAGE_SIZE, DUMMY_IMAGE_SIZE) and 0.0 <= float(drafts.min())
    np.testing.assert_array_equal(fitted, [10.0, 200.0])
    proxied = run(pipe, images, start_from="proxy", input_azimuth_deg=[10.0, 200.0],
                  input_depression_deg=17.0, **kwargs)  # fmt: skip
    torch.testing.assert_close(proxied, run(pipe, images, start_image=drafts, **kwargs))
    # the proxy settings travel with the pipeline
    pipe.save_pretrained(tmp_path)
    loaded = SARZero123Pipeline.from_pretrained(tmp_path)
    assert loaded.config.proxy == {**SMALL_PROXY, "shortlist": 0, "retrieval": None}  # the fields it left out
    # refusals name what to pass
    with pytest.raises(ValueError, match=r"`input_depression_deg`: start_from='proxy' fits"):
        run(pipe, images, start_from="proxy", input_azimuth_deg=10.0, **kwargs)
    with pytest.raises(ValueError, match=r"`input_azimuth_deg`: start_from='proxy' fits .*; give each input"):
        run(pipe, images, start_from="proxy", input_depression_deg=17.0, **kwargs)
    with pytest.raises(ValueError, match=r"`input_azimuth_deg` has 3 values; expected 1 or one per input"):
        run(pipe, images, start_from="proxy", input_azimuth_deg=[1.0, 2.0, 3.0], input_depression_deg=17.0,
            **kwargs)  # fmt: skip
    with pytest.raises(ValueError, match=r"`input_azimuth_deg` must be finite"):  # checked though unused
        run(pipe, images, input_azimuth_deg=float("nan"), **kwargs)
    for value in (0.0, 0.5, 1.0):  # a chip with no structure matches every vehicle equally: refused
        flat = torch.cat([images[:1], torch.full_like(images[:1], value)])
        with pytest.raises(ValueError, match=rf"image: input 1 has no structure .*every pixel {value:g}\)"):
            run(pipe, flat, start_from="proxy", input_azimuth_deg=10.0, input_depression_deg=17.0, **kwargs)
    plain = SARZero123Pipeline(**get_dummy_components())
    with pytest.raises(ValueError, match=r"records no proxy settings"):
        run(plain, images, start_from="proxy", input_azimuth_deg=10.0, input_depression_deg=17.0, **kwargs)


def test_a_recorded_proxy_start_uses_the_proxy_when_the_azimuth_is_given_and_the_input_otherwise():
    sampler = {"num_inference_steps": 4, "strength": 0.75, "start_from": "proxy", "proxy_strength": 0.5}
    pipe = SARZero123Pipeline(**get_dummy_components(), sampler=sampler, proxy=SMALL_PROXY)
    pipe.set_progress_bar_config(disable=True)
    images = dummy_images(batch_size=2, seed=4)
    kwargs = {"d_az": [60.0, 120.0], "num_inference_steps": None, "output_type": "latent"}
    explicit = {**kwargs, "num_inference_steps": 4, "strength": 0.5}
    with_azimuth = run(pipe, images, input_azimuth_deg=[0.0, 90.0], input_depression_deg=17.0, **kwargs)
    proxied = run(pipe, images, start_from="proxy", input_azimuth_deg=[0.0, 90.0], input_depression_deg=17.0,
                  **explicit)  # fmt: skip
    torch.testing.assert_close(with_azimuth, proxied)
    from_input = {**explicit, "strength": 0.75}  # no azimuth: the input, at the recorded strength
    plain = run(pipe, images, **kwargs)
    torch.testing.assert_close(plain, run(pipe, images, start_from="input", **from_input))
    # a recorded strength runs at least one step of the call's own count (0.5 x 1 step would run none)
    pose = {"input_azimuth_deg": 0.0, "input_depression_deg": 17.0}
    one_step = run(pipe, images, **pose, **{**kwargs, "num_inference_steps": 1})
    assert one_step.shape == with_azimuth.shape
    with pytest.raises(ValueError, match=r"strength 0.5 x num_inference_steps 1 leaves no denoising step"):
        run(pipe, images, **{**explicit, "num_inference_steps": 1})  # an explicit strength is never changed


def test_a_folder_naming_a_module_outside_the_component_libraries_is_refused_before_any_import(
    pipe, tmp_path, capsys
):
    """A model_index.json is data: ["this", "s"] would import the module `this` (printing the Zen of
    Python)."""
    pipe.save_pretrained(tmp_path)
    index_path = tmp_path / "model_index.json"
    model_index = json.loads(index_path.read_text())
    model_index["pose_projection"] = ["this", "s"]
    index_path.write_text(json.dumps(model_index))
    with pytest.raises(ValueError, match=r"model_index.json' has \d+ bytes, manifest.json records"):
        SARZero123Pipeline.from_pretrained(tmp_path)
    with pytest.raises(ValueError, match=r"listed as this.s; a component must come from one of"):
        SARZero123Pipeline.from_pretrained(tmp_path, verify_manifest=False)  # the allow-list holds even so
    assert "Beautiful is better than ugly" not in capsys.readouterr().out


def test_one_chip_asked_for_several_views_is_fitted_once(monkeypatch):
    """generate and the demo's turntable send one chip with many requests: one fit, one render per view; a
    later call on the same chip and pose reuses the fit."""
    from sar_zero123.model.proxy import _fit, draft_target_views, proxy_bank

    _fit.cache_clear()

    bank = proxy_bank(*(SMALL_PROXY[key] for key in ("num_vehicles", "first_seed", "blur_sigma_px",
                                                      "render_seed", "max_shift_px")), 0)  # fmt: skip
    calls = []
    original = bank.scores_and_shifts
    monkeypatch.setattr(bank, "scores_and_shifts", lambda *a, **k: calls.append(a) or original(*a, **k))
    images = dummy_images(batch_size=1, seed=5).expand(3, -1, -1, -1)
    drafts, _ = draft_target_views(images, torch.full((3,), 40.0), torch.full((3,), 17.0),
                                   torch.tensor([0.0, 90.0, 180.0]), torch.zeros(3), SMALL_PROXY)  # fmt: skip
    assert len(calls) == 1 and drafts.shape == (3, 1, DUMMY_IMAGE_SIZE, DUMMY_IMAGE_SIZE)
    assert not torch.equal(drafts[0], drafts[1])  # each view its own render
    one = torch.tensor
    again, _ = draft_target_views(images[:1], one([40.0]), one([17.0]), one([90.0]), one([0.0]), SMALL_PROXY)
    assert len(calls) == 1 and torch.equal(again[0], drafts[1])  # a later call on the chip: remembered


@pytest.mark.parametrize(
    ("name", "match"),
    [("sim-prior-rotated", r"did you mean 'sar-zero123/sim-prior-rotated'\?"),
     ("SAR-ZERO123/sim-prior-identity", r"did you mean 'sar-zero123/sim-prior-identity'\?"),
     ("./nope", r"'./nope': no such pipeline folder"), ("/no/such/folder", r"no such pipeline folder")],
)  # fmt: skip
def test_a_missing_local_name_lists_the_bundled_pipelines_instead_of_a_hub_error(name, match):
    with pytest.raises(FileNotFoundError, match=match) as error:
        SARZero123Pipeline.from_pretrained(name)
    assert "sar-zero123/sim-prior-rotated" in str(error.value)


def test_a_bad_generator_or_callback_is_refused_by_name(pipe):
    for generator in (42, [1], [torch.Generator(), None]):
        with pytest.raises(ValueError, match=r"`generator` must be a torch.Generator or a list of them"):
            run(pipe, generator=generator)
    with pytest.raises(ValueError, match="`callback_on_step_end` must return a dict"):
        run(pipe, callback_on_step_end=lambda p, step, t, kwargs: None)
    with pytest.raises(ValueError, match=r"`callback_on_step_end` returned latents \(1,\); expected a"):
        run(pipe, callback_on_step_end=lambda p, step, t, kwargs: {"latents": torch.zeros(1)})
    # a callback that hands the latents back unchanged, or changes nothing, leaves the views as they were
    plain = run(pipe)
    torch.testing.assert_close(run(pipe, callback_on_step_end=lambda p, step, t, kwargs: kwargs), plain)
    torch.testing.assert_close(run(pipe, callback_on_step_end=lambda p, step, t, kwargs: {}), plain)


@pytest.mark.parametrize("name", ["scheduler", "vae", "unet"])
def test_a_missing_component_is_refused_by_name(name):
    components = {**get_dummy_components(), name: None}
    with pytest.raises(ValueError, match=rf"`{name}` must be a diffusers \w+, got NoneType"):
        SARZero123Pipeline(**components)
