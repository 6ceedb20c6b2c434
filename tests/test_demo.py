"""The demo page (issue 38 item 5): the model behind it without a browser, then the page in headless
Chromium as a user would drive it (skipped without the [demo] extra, playwright or a chromium binary)."""

from __future__ import annotations

import base64
import dataclasses
import io
import os
import re
import shutil
import socket
import time

import numpy as np
import pytest
from PIL import Image

from sar_zero123.demo import MAX_UPLOAD_BYTES, TURNTABLE_VIEWS, DemoModel, main, parse_args, to_uint8
from sar_zero123.model.sampler import SamplerSettings
from sar_zero123.pretrained import SIM_PRIOR_ROTATED
from sar_zero123.sim import make_target, render_chip


@pytest.fixture(scope="module")
def model() -> DemoModel:
    return DemoModel(sampler=SamplerSettings(num_inference_steps=2))


def test_a_simulated_vehicle_its_views_and_its_truth(model):
    chip = model.simulated_chip("TANK", 30.0, 17.0)
    expected = render_chip(make_target("TANK"), azimuth_deg=90.0, depression_deg=27.0, size=64,
                           generator=np.random.default_rng(0))  # fmt: skip
    np.testing.assert_allclose(model.truth(chip, 60.0, 10.0), model.scaling.normalize(expected), atol=1e-6)
    views = model.views(chip, [60.0, -30.0], 10.0, seed=3)
    assert views.shape == (2, 64, 64) and 0.0 <= views.min() and views.max() <= 1.0
    # seeded per view: alone it is the same view, up to the float rounding of another batch size
    np.testing.assert_allclose(views[:1], model.views(chip, [60.0], 10.0, seed=3), atol=2e-3)
    strip = model.turntable(chip, 0.0, seed=3)
    assert strip.shape == (64, 64 * TURNTABLE_VIEWS)
    # tile k is the view turned by k * 360 / TURNTABLE_VIEWS deg, with that view's own generator
    np.testing.assert_allclose(strip[:, 64:128], model.views(chip, [0.0, 45.0], 0.0, seed=3)[1], atol=2e-3)
    assert to_uint8(strip[:, :64]).shape == (256, 256)
    # a simulated chip's azimuth is known: the bundled prior starts from its proxy; without it, from noise
    unknown = dataclasses.replace(chip, azimuth_deg=None)
    from_noise = model.views(unknown, [60.0, -30.0], 10.0, seed=3)
    assert np.abs(from_noise - views).max() > 1e-2
    unguided_level = model.views(unknown, [0.0, 45.0], 0.0, seed=3)[1]
    # depression guidance reaches the pipeline: a depression request moves, a level one does not
    model.sampler = dataclasses.replace(model.sampler, depression_guidance_scale=3.0)
    try:
        level = model.views(unknown, [0.0, 45.0], 0.0, seed=3)[1]
        np.testing.assert_allclose(level, unguided_level, atol=2e-3)
        assert np.abs(model.views(unknown, [60.0, -30.0], 10.0, seed=3) - from_noise).max() > 1e-3
    finally:
        model.sampler = dataclasses.replace(model.sampler, depression_guidance_scale=None)


def test_the_command_with_no_options_leaves_the_sampler_to_the_pipeline_and_refuses_bad_values(capsys):
    args = parse_args([])
    assert args.sampler_settings() == SamplerSettings()  # every sampler field left to the pipeline
    assert (args.pipeline, args.host, args.port, args.share) == (SIM_PRIOR_ROTATED, "127.0.0.1", 7860, False)
    assert parse_args(["--num-inference-steps", "7", "--start_from", "proxy"]).sampler_settings() == (
        SamplerSettings(num_inference_steps=7, start_from="proxy")
    )
    expected = ("num_inference_steps must be an integer in [1, 1,000], got 0",
                "heading_guidance_scale must lie in [0, 100], got -1.0",
                "port must lie in [1, 65535], got 0")  # fmt: skip
    bad_flags = (["--num_inference_steps", "0"], ["--heading_guidance_scale", "-1"], ["--port", "0"])
    for bad, message in zip(bad_flags, expected):
        with pytest.raises(ValueError, match=re.escape(message)):
            parse_args(bad)
        with pytest.raises(SystemExit) as done:  # the command refuses it in one line
            main(bad)
        assert done.value.code == 2
        assert capsys.readouterr().err == f"sar-zero123-demo: error: {message}\n"


def test_bad_uploads_and_requests_are_refused_with_a_message(model, tmp_path):
    broken = tmp_path / "chip.png"
    broken.write_bytes(b"not an image")
    with pytest.raises(ValueError, match="cannot read the .png image"):
        model.uploaded_chip(broken, 17.0)
    big = tmp_path / "big.npy"
    big.write_bytes(b"\0" * (MAX_UPLOAD_BYTES + 1))
    with pytest.raises(ValueError, match=r"the file is 5.2 MB; chips up to 5 MB are accepted"):
        model.uploaded_chip(big, 17.0)
    bright = tmp_path / "bright.npy"
    np.save(bright, np.full((64, 64), 500.0, dtype=np.float32))
    with pytest.raises(ValueError, match=r"100.0% of the pixels lie outside the scaling's dB range"):
        model.uploaded_chip(bright, 17.0)
    path = _chip_file(tmp_path)
    chip = model.uploaded_chip(path, 17.0)
    assert chip.image.shape == (64, 64) and model.truth(chip, 30.0, 0.0) is None
    np.testing.assert_allclose(chip.image, model.scaling.normalize(np.load(path)), atol=1e-6)
    with pytest.raises(
        ValueError, match=r"target depressions \(input \+ d_el\) \[62.0\] deg lie outside .* \[10, 60\]"
    ):
        model.views(chip, [30.0], 45.0)
    with pytest.raises(
        ValueError, match=r"d_el: \[60.0\] deg lie outside the range the pipeline was trained on, \[-50, 50\]"
    ):
        model.views(chip, [30.0], 60.0)
    with pytest.raises(ValueError, match=r"vehicle must be one of"):
        model.simulated_chip("BOAT", 0.0, 17.0)


def _chip_file(folder):
    path = folder / "tank.npy"
    np.save(path, render_chip(make_target("TANK"), azimuth_deg=10.0, depression_deg=17.0, size=64,
                              generator=np.random.default_rng(1)))  # fmt: skip
    return path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _image_of(page, selector: str) -> np.ndarray:
    source = page.locator(f"{selector} img").first.get_attribute("src")
    if source.startswith("data:"):
        data = base64.b64decode(source.split(",", 1)[1])
    else:
        data = page.request.get(source).body()
    return np.asarray(Image.open(io.BytesIO(data)).convert("L"))


def test_the_page_in_a_browser_generates_a_view_and_explains_a_bad_upload(model, tmp_path):
    pytest.importorskip("gradio")
    playwright = pytest.importorskip("playwright.sync_api")
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("no chromium binary (Debian: apt install chromium)")
    from sar_zero123.demo import build_demo

    demo = build_demo(model)
    port = _free_port()
    demo.launch(server_name="127.0.0.1", server_port=port, prevent_thread_lock=True, share=False,
                max_file_size=MAX_UPLOAD_BYTES, show_api=False, quiet=True)  # fmt: skip
    try:
        assert demo.share is False and demo.server_name == "127.0.0.1"
        with playwright.sync_playwright() as driver:
            browser = driver.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.goto(f"http://127.0.0.1:{port}/")
            page.click("#generate")
            page.wait_for_selector("#view_image img", timeout=60_000)
            page.wait_for_selector("#truth_image img", timeout=60_000)
            view = _image_of(page, "#view_image")
            assert view.shape == (256, 256) and view.std() > 5  # a 64 px view shown at 4x, not blank
            assert _image_of(page, "#truth_image").shape == (256, 256)
            if os.environ.get("SAR_ZERO123_DEMO_SCREENSHOT"):
                page.screenshot(path=os.environ["SAR_ZERO123_DEMO_SCREENSHOT"], full_page=True)
            # a malformed upload: a message on the page, not a stack trace
            broken = tmp_path / "chip.png"
            broken.write_bytes(b"not an image")
            page.get_by_role("radio", name="upload").check()
            page.locator("input[type=file]").set_input_files(str(broken))
            page.wait_for_timeout(1000)
            page.click("#generate")
            page.get_by_text("cannot read the .png image").first.wait_for(timeout=30_000)
            browser.close()
    finally:
        demo.close()


def test_the_served_page_loads_nothing_from_outside_the_machine():
    from sar_zero123.demo import strip_external_resources

    page = (
        '<head><link rel="preconnect" href="https://fonts.googleapis.com" />'
        '<link rel="stylesheet" href="./assets/index.css">'
        '<script src="https://cdnjs.cloudflare.com/ajax/libs/x.js" async></script>'
        '<script type="module" src="./assets/index.js"></script>'
        '<meta property="og:image" content="https://raw.githubusercontent.com/a.jpg" />'
        '<meta charset="utf-8" /></head>'
    )
    assert strip_external_resources(page) == (
        '<head><link rel="stylesheet" href="./assets/index.css">'
        '<script type="module" src="./assets/index.js"></script><meta charset="utf-8" /></head>'
    )


def test_the_local_app_serves_a_page_without_external_addresses(model):
    pytest.importorskip("gradio")
    import threading
    import urllib.request

    import uvicorn

    from sar_zero123.demo import build_demo, local_app

    port = _free_port()
    server = uvicorn.Server(uvicorn.Config(local_app(build_demo(model)), host="127.0.0.1", port=port,
                                           log_level="warning"))  # fmt: skip
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        for _ in range(100):
            if server.started:
                break
            time.sleep(0.1)
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}/").read().decode()
        # no tag that makes the browser contact another host (the app's config data may name addresses)
        assert "gradio" in page and "fonts.googleapis" not in page and "cdnjs" not in page
        assert re.search(r"<(link|script|meta)\b[^>]*\b(href|src|content)=[\"']https?://", page) is None
    finally:
        server.should_exit = True
        thread.join(timeout=10)


def test_an_upload_switches_the_input_to_it(model):
    """A file uploaded while the input choice is left on "simulated vehicle" is the input from then on: the
    upload event sets the choice to "upload", so the page generates from the file it shows."""
    gr = pytest.importorskip("gradio")
    from sar_zero123.demo import build_demo

    demo = build_demo(model)
    choice = next(b for b in demo.blocks.values() if isinstance(b, gr.Radio) and b.label == "input")
    assert choice.value == "simulated vehicle"
    switches = [fn for fn in demo.fns.values()
                if any(event == "upload" for _, event in fn.targets) and choice in fn.outputs]  # fmt: skip
    assert len(switches) == 1
    assert switches[0].fn("chip.png") == "upload"
