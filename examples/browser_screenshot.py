"""Screenshots of a web page in headless Chromium (Debian's chromium + chromium-driver, driven by
selenium): the viewer's browser test and the README's viewer picture use it."""

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)


def chromium_available() -> bool:
    return Path(CHROMIUM).is_file() and Path(CHROMEDRIVER).is_file()


def screenshot_when(
    url: str,
    path: Path,
    ready,
    timeout: float = 120.0,
    size: tuple[int, int] = (1200, 800),
    settle: float = 1.0,
    script: str | None = None,
) -> np.ndarray:
    """Load `url`, then screenshot it every second until `ready(pixels)` holds (or the timeout
    passes); the last screenshot is written to `path` and returned as uint8 [H, W, 3]. `script`:
    JavaScript run before each screenshot (to close a notification, say)."""
    from PIL import Image
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="chromium-profile-")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*FLAGS, f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        driver.get(url)
        deadline = time.monotonic() + timeout
        while True:
            time.sleep(settle)
            if script:
                driver.execute_script(script)
            driver.save_screenshot(str(path))
            pixels = np.asarray(Image.open(path).convert("RGB"))
            if ready(pixels) or time.monotonic() > deadline:
                return pixels
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)
