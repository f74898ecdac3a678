"""Where the browser tests find Chromium and Playwright: Debian's Chromium (``apt-get install
chromium``) driven by Playwright (``pip install playwright``, no ``playwright install``: the system
browser is used). ``BROWSER_SKIPS`` skips a test with the missing piece named."""

import importlib.util
import os
import shutil

import pytest

CHROMIUM_CANDIDATES = ("/usr/lib/chromium/chromium", "chromium", "chromium-browser", "google-chrome")


def find_chromium():
    """The browser binary: ``INFINIRL_CHROMIUM`` if set, else Debian's (the binary itself, not the
    /usr/bin/chromium launcher script), else one on PATH."""
    for candidate in (os.environ.get("INFINIRL_CHROMIUM"), *CHROMIUM_CANDIDATES):
        path = candidate and (candidate if os.path.isfile(candidate) else shutil.which(candidate))
        if path:
            return path
    return None


CHROMIUM = find_chromium()
BROWSER_SKIPS = [
    pytest.mark.skipif(importlib.util.find_spec("playwright") is None,
                       reason="needs Playwright: pip install playwright (the system Chromium is used)"),
    pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium: apt-get install chromium (or set INFINIRL_CHROMIUM)"),
]
BROWSER_AVAILABLE = CHROMIUM is not None and importlib.util.find_spec("playwright") is not None
# A test of a page's API that its browser twin repeats click for click: the default tier runs the
# API one only where the browser one is skipped (pytest -m slow runs both).
COVERED_BY_THE_BROWSER = [pytest.mark.slow] if BROWSER_AVAILABLE else []
