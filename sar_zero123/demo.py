"""A local web page to look at novel views: ``python -m sar_zero123.demo`` or ``sar-zero123-demo`` (needs the
``[demo]`` extra).

The user uploads a chip or picks a simulated vehicle, sets the pose changes with sliders, and sees the
generated view beside the input (and the simulator's truth), plus a 360 deg turntable strip.

Safe by default: it binds to 127.0.0.1 unless ``--host`` says otherwise, opens a public link only with
``--share``, bounds uploads and the queue, answers bad input with a message on the page, never a stack
trace, and contacts nothing outside the machine (no analytics, version check or web fonts). The page is
a thin shell over :class:`DemoModel`, plain functions of numpy arrays tested without a browser.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sar_zero123.augment_dataset.plan import check_trained_ranges
from sar_zero123.config import parse_config
from sar_zero123.data import DecibelScaling
from sar_zero123.generate import GenerateConfig, load_input_chip
from sar_zero123.model.pipeline import SARZero123Pipeline
from sar_zero123.model.sampler import SamplerSettings
from sar_zero123.pretrained import SIM_PRIOR_ROTATED, resolve_pretrained
from sar_zero123.runs.refusals import REFUSED
from sar_zero123.sim import TARGET_CLASSES, make_target, render_chip

__all__ = [
    "MAX_QUEUED", "MAX_UPLOAD_BYTES", "TURNTABLE_VIEWS", "DemoConfig", "DemoModel", "build_demo", "main",
    "parse_args",
]  # fmt: skip

#: The page's fonts: the system's own, so that the browser fetches nothing from the web.
LOCAL_FONTS = ("system-ui", "sans-serif")
LOCAL_MONO_FONTS = ("ui-monospace", "monospace")
#: Largest upload the page accepts (an MSTAR chip file is about 130 kB; a 128 px PNG a few kB).
MAX_UPLOAD_BYTES = 5 * 1024 * 1024
#: Requests that may wait for the one generation running; more are refused with a message.
MAX_QUEUED = 8
#: Views of the turntable strip (every 360 / TURNTABLE_VIEWS deg).
TURNTABLE_VIEWS = 8


@dataclass(frozen=True)
class Chip:
    """An input chip in the pipeline's normalised dB, with its depression and, when simulated, how to
    render its truth at another pose."""

    image: np.ndarray  # (S, S) float32 normalised dB in [0, 1]
    depression_deg: float  # the chip's absolute depression
    target_class: str | None = None  # simulated vehicle, or None for an upload
    azimuth_deg: float | None = None  # its azimuth, for the truth
    seed: int = 0  # the simulator's clutter and speckle seed


@dataclass
class DemoConfig(SamplerSettings):
    """Serve a local web page that generates novel views of a chip with a saved SARZero123Pipeline.

    Sampler fields left unset take the pipeline's recorded values, else the library's.
    """

    pipeline: str = SIM_PRIOR_ROTATED  # bundled name or pipeline folder
    host: str = "127.0.0.1"  # address to bind (127.0.0.1: this machine only)
    port: int = 7860  # port
    share: bool = False  # also open a public gradio.live link
    device: str = "cpu"  # torch device

    def __post_init__(self) -> None:
        super().__post_init__()  # the sampler's fields, validated where they are declared
        if isinstance(self.port, bool) or not 0 < self.port < 65536:
            raise ValueError(f"port must lie in [1, 65535], got {self.port}")


class DemoModel:
    """The pipeline and what the page asks of it.

    Args:
        pipeline: A bundled pipeline's name or a ``save_pretrained`` folder.
        sampler: How every view is sampled; a field left ``None`` is the pipeline's recorded value, and its
            ``scheduler`` swaps the pipeline's.
    """

    def __init__(
        self, pipeline: str = SIM_PRIOR_ROTATED, sampler: SamplerSettings | None = None, device: str = "cpu"
    ) -> None:
        self.sampler = SamplerSettings() if sampler is None else sampler.sampler_settings()
        self.name = pipeline
        self.pipe = SARZero123Pipeline.from_pretrained(pipeline).to(device)
        self.pipe.set_progress_bar_config(disable=True)
        self.sampler.apply_scheduler(self.pipe)
        self.size = self.pipe.default_image_size
        scaling_file = resolve_pretrained(pipeline) / "decibel_scaling.json"
        self.scaling = (
            DecibelScaling.from_file(scaling_file)
            if scaling_file.is_file()
            else DecibelScaling.for_unit_magnitude()
        )
        # the page says how many steps
        self.num_inference_steps = self.sampler.resolved(self.pipe.config.sampler)["num_inference_steps"]
        config = self.pipe.pose_projection.config
        self.needs_depression = bool(getattr(config, "input_depression", False))
        self.trained_depression_deg = getattr(config, "trained_depression_deg", None) or [1.0, 89.0]
        self.trained_d_el_deg = getattr(config, "trained_d_el_deg", None) or [-30.0, 30.0]

    # ------------------------------------------------------------------------------------------ inputs
    def uploaded_chip(self, path: str | Path, depression_deg: float) -> Chip:
        """An uploaded chip file as the pipeline's input.

        Raises:
            ValueError: For a file that is too large, or that ``sar-zero123-generate`` would refuse.
        """
        path = Path(path)
        if path.stat().st_size > MAX_UPLOAD_BYTES:
            raise ValueError(
                f"the file is {path.stat().st_size / 1e6:.1f} MB; chips up to "
                f"{MAX_UPLOAD_BYTES / 1e6:.0f} MB are accepted"
            )
        chip = load_input_chip(GenerateConfig(pipeline=self.name, image=str(path)), self.size)
        return Chip(chip, float(depression_deg))

    def simulated_chip(
        self, target_class: str, azimuth_deg: float, depression_deg: float, seed: int = 0
    ) -> Chip:
        """A chip of a built-in simulated vehicle (:data:`~sar_zero123.sim.TARGET_CLASSES`)."""
        if target_class not in TARGET_CLASSES:
            raise ValueError(f"vehicle must be one of {sorted(TARGET_CLASSES)}, got {target_class!r}")
        magnitude = self._render(target_class, azimuth_deg, depression_deg, seed)
        return Chip(self.scaling.normalize(magnitude).astype(np.float32), float(depression_deg), target_class,
                    float(azimuth_deg), seed)  # fmt: skip

    def truth(self, chip: Chip, d_az: float, d_el: float) -> np.ndarray | None:
        """The simulator's view at the requested pose (normalised dB), or None for an upload."""
        if chip.target_class is None or chip.azimuth_deg is None:
            return None
        azimuth = (chip.azimuth_deg + d_az) % 360.0
        magnitude = self._render(chip.target_class, azimuth, chip.depression_deg + d_el, chip.seed)
        return self.scaling.normalize(magnitude).astype(np.float32)

    def _render(self, target_class: str, azimuth_deg: float, depression_deg: float, seed: int) -> np.ndarray:
        target = make_target(target_class)
        return render_chip(target, azimuth_deg=float(azimuth_deg), depression_deg=float(depression_deg),
                           size=self.size, generator=np.random.default_rng(seed))  # fmt: skip

    # ------------------------------------------------------------------------------------------ views
    def check_request(self, chip: Chip, d_el: float) -> None:
        """Refuse a request outside the pipeline's trained ranges (the check ``augment_dataset`` makes)."""
        check_trained_ranges(self.pipe.pose_projection.config, [d_el], [chip.depression_deg])

    def views(self, chip: Chip, d_az: Sequence[float], d_el: float, seed: int = 0) -> np.ndarray:
        """Generated views at each ``d_az`` (one batched call), ``(N, S, S)`` normalised dB in [0, 1]."""
        self.check_request(chip, d_el)
        image = torch.from_numpy(chip.image)[None, None].repeat(len(d_az), 1, 1, 1)
        generator = [torch.Generator().manual_seed(seed + i) for i in range(len(d_az))]
        output = self.pipe(
            image, d_az=[float(a) for a in d_az], d_el=[float(d_el)] * len(d_az),
            # with its azimuth (simulated chips), a pipeline that records a proxy start starts from the proxy
            input_depression_deg=chip.depression_deg if self.needs_depression or chip.azimuth_deg is not None
            else None, input_azimuth_deg=chip.azimuth_deg, generator=generator, output_type="np",
            **self.sampler.sampler_arguments(),
        )  # fmt: skip
        return np.clip(output.images[..., 0], 0.0, 1.0).astype(np.float32)

    def turntable(self, chip: Chip, d_el: float, seed: int = 0) -> np.ndarray:
        """The input turned by every ``360 / TURNTABLE_VIEWS`` deg, side by side: ``(S, N * S)``."""
        steps = [360.0 * k / TURNTABLE_VIEWS for k in range(TURNTABLE_VIEWS)]
        return np.concatenate(list(self.views(chip, steps, d_el, seed)), axis=1)


def to_uint8(image: np.ndarray, scale: int = 4) -> np.ndarray:
    """Normalised dB in [0, 1] as an 8-bit image, each pixel ``scale`` x ``scale`` (64 px chips are small)."""
    pixels = (np.clip(image, 0.0, 1.0) * 255.0).round().astype(np.uint8)
    return np.kron(pixels, np.ones((scale, scale), dtype=np.uint8))


def build_demo(model: DemoModel) -> Any:
    """The page (a ``gradio.Blocks``) over ``model``; ``.launch()`` serves it. It contacts nothing outside
    the machine: no analytics, no version check, the system's fonts."""
    os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")  # read when gradio is imported
    import gradio as gr

    low, high = model.trained_d_el_deg
    depression_low, depression_high = model.trained_depression_deg
    default_depression = min(max(17.0, depression_low), depression_high)

    def chip_of(source: str, upload: str | None, vehicle: str, azimuth: float, depression: float) -> Chip:
        try:
            if source == "upload":
                if upload is None:
                    raise ValueError(
                        "upload a chip file first (PNG, .npy or an MSTAR file), or pick a vehicle"
                    )
                return model.uploaded_chip(upload, depression)
            return model.simulated_chip(vehicle, azimuth, depression)
        except (ValueError, FileNotFoundError, OSError) as error:
            raise gr.Error(str(error)) from None

    def generate(source, upload, vehicle, azimuth, depression, d_az, d_el, seed):
        chip = chip_of(source, upload, vehicle, azimuth, depression)
        try:
            view = model.views(chip, [d_az], d_el, int(seed))[0]
        except ValueError as error:
            raise gr.Error(str(error)) from None
        truth = model.truth(chip, d_az, d_el)
        return to_uint8(chip.image), to_uint8(view), None if truth is None else to_uint8(truth)

    def turntable(source, upload, vehicle, azimuth, depression, d_el, seed):
        chip = chip_of(source, upload, vehicle, azimuth, depression)
        try:
            return to_uint8(model.turntable(chip, d_el, int(seed)), scale=2)
        except ValueError as error:
            raise gr.Error(str(error)) from None

    local_theme = gr.themes.Default(font=LOCAL_FONTS, font_mono=LOCAL_MONO_FONTS)  # no web fonts
    with gr.Blocks(title="sar_zero123: novel SAR views", analytics_enabled=False, theme=local_theme) as demo:
        gr.Markdown(
            f"## Novel views of a SAR chip\nPipeline `{model.name}`, {model.num_inference_steps} denoising "
            "steps. Pick a simulated vehicle or upload a chip, set the azimuth and depression changes, "
            "and generate."
        )
        with gr.Row():
            with gr.Column():
                source = gr.Radio(["simulated vehicle", "upload"], value="simulated vehicle", label="input")
                vehicle = gr.Dropdown(sorted(TARGET_CLASSES), value="TANK", label="simulated vehicle")
                azimuth = gr.Slider(0, 359, value=30, step=1, label="its azimuth (deg)")
                upload = gr.File(label="chip file (PNG, .npy, MSTAR)", type="filepath")
                depression = gr.Slider(depression_low, depression_high, value=default_depression, step=0.5,
                                       label="input depression (deg)")  # fmt: skip
                d_az = gr.Slider(-180, 180, value=60, step=1, label="azimuth change d_az (deg)")
                d_el = gr.Slider(low, high, value=0.0, step=0.5, label="depression change d_el (deg)")
                seed = gr.Number(0, precision=0, label="seed")
                with gr.Row():
                    go = gr.Button("Generate", variant="primary", elem_id="generate")
                    spin = gr.Button("Turntable (360 deg)", elem_id="turntable")
            with gr.Column():
                with gr.Row():
                    shown_input = gr.Image(label="input", elem_id="input_image")
                    shown_view = gr.Image(label="generated view", elem_id="view_image")
                    shown_truth = gr.Image(label="simulator truth", elem_id="truth_image")
                strip = gr.Image(label="turntable", elem_id="turntable_image")
        # a file uploaded is the input from then on (the choice is switched, so the page shows it)
        upload.upload(lambda _: "upload", upload, source)
        inputs = [source, upload, vehicle, azimuth, depression]
        go.click(generate, [*inputs, d_az, d_el, seed], [shown_input, shown_view, shown_truth])
        spin.click(turntable, [*inputs, d_el, seed], [strip])
    demo.queue(default_concurrency_limit=1, max_size=MAX_QUEUED)
    return demo


def parse_args(argv: Sequence[str] | None = None) -> DemoConfig:
    """The demo's flags, parsed and checked as every command's are (:func:`~sar_zero123.config.parse_config`).

    Raises:
        ValueError: Naming the flag, for a bad value.
    """
    return parse_config(DemoConfig, argv, prog="sar-zero123-demo")


#: What the served page may load from outside this machine: nothing. Tags gradio's page template adds that
#: would (font preconnects, an iframe-resizer script from a CDN, a preview image's address) are removed.
_EXTERNAL_TAGS = (
    re.compile(r"<link\b[^>]*\bhref=[\"']https?://[^>]*>", re.IGNORECASE),
    re.compile(r"<script\b[^>]*\bsrc=[\"']https?://[^>]*>\s*</script>", re.IGNORECASE),
    re.compile(r"<meta\b[^>]*\bcontent=[\"']https?://[^>]*>", re.IGNORECASE),
)


def strip_external_resources(html: str) -> str:
    """``html`` without the tags whose absolute ``http(s)://`` address makes a browser contact another
    host."""
    for pattern in _EXTERNAL_TAGS:
        html = pattern.sub("", html)
    return html


def local_app(demo: Any) -> Any:
    """A FastAPI app serving ``demo`` whose HTML pages load nothing from outside the machine."""
    import gradio as gr
    from fastapi import FastAPI, Request, Response

    app = FastAPI()

    @app.middleware("http")
    async def local_only(request: Request, call_next: Any) -> Any:
        response = await call_next(request)
        if not response.headers.get("content-type", "").startswith("text/html"):
            return response
        body = b"".join([chunk async for chunk in response.body_iterator])
        headers = {k: v for k, v in response.headers.items() if k.lower() != "content-length"}
        page = strip_external_resources(body.decode("utf-8", errors="replace"))
        return Response(page, status_code=response.status_code, headers=headers, media_type="text/html")

    return gr.mount_gradio_app(app, demo, path="/", max_file_size=MAX_UPLOAD_BYTES, show_api=False)


def main(argv: Sequence[str] | None = None) -> None:
    """Serve the page until interrupted; a bad flag is refused in one line (exit status 2)."""
    try:
        args = parse_args(argv)
    except ValueError as error:
        print(f"sar-zero123-demo: error: {error}", file=sys.stderr)
        raise SystemExit(REFUSED) from None
    try:
        import gradio  # noqa: F401
    except ImportError:
        raise SystemExit("the demo needs gradio: pip install -e '.[demo]'") from None
    model = DemoModel(args.pipeline, args.sampler_settings(), args.device)
    demo = build_demo(model)
    if args.share:  # a public link is gradio's own server (and contacts gradio's share servers by design)
        demo.launch(server_name=args.host, server_port=args.port, share=True, max_file_size=MAX_UPLOAD_BYTES,
                    show_api=False)  # fmt: skip
        return
    import uvicorn

    print(f"serving http://{args.host}:{args.port} (this machine only unless --host says otherwise)")
    uvicorn.run(local_app(demo), host=args.host, port=args.port, log_level="warning")


if __name__ == "__main__":
    main()
