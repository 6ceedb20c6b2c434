"""The README's screenshot of the demo page, taken in headless Chromium as a user would see it.

    python benchmarks/demo_screenshot.py docs/figures/demo.png

Needs the ``[demo]`` extra, ``pip install playwright`` and a chromium binary (Debian: ``apt install
chromium``). Serves the page on a free local port (bundled ``sar-zero123/sim-prior-rotated``, 20 denoising
steps), clicks "Generate" (a TANK at 30 deg azimuth, 17 deg depression, turned by 60 deg) and "Turntable",
and saves the page.
"""

from __future__ import annotations

import shutil
import socket
import sys
from pathlib import Path

from playwright.sync_api import sync_playwright

from sar_zero123.demo import MAX_UPLOAD_BYTES, DemoModel, build_demo


def main(path: Path) -> None:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("no chromium binary (Debian: apt install chromium)")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    demo = build_demo(DemoModel(num_inference_steps=20))
    demo.launch(server_name="127.0.0.1", server_port=port, prevent_thread_lock=True, share=False,
                max_file_size=MAX_UPLOAD_BYTES, show_api=False, quiet=True)  # fmt: skip
    try:
        with sync_playwright() as driver:
            browser = driver.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.goto(f"http://127.0.0.1:{port}/")
            page.click("#generate")
            page.wait_for_selector("#truth_image img", timeout=120_000)
            page.click("#turntable")
            page.wait_for_selector("#turntable_image img", timeout=300_000)
            page.wait_for_timeout(500)
            page.screenshot(path=str(path), full_page=True)
            browser.close()
    finally:
        demo.close()
    print(f"wrote {path}")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "demo.png"))
