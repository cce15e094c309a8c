"""The headless browser of the browser tests: Debian's ``chromium`` driven by Playwright from the package index
(run.sh installs both; Playwright never downloads a browser of its own)."""

from __future__ import annotations

import os
import shutil

import pytest

CHROMIUM = os.environ.get("SP_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
"""Debian's chromium (run.sh installs it); ``SP_CHROMIUM`` names another Chromium build."""
# FINDINGS.md, 2026-12-05: what runs here (no GPU, no sandbox for root, no network)
CHROMIUM_ARGS = [
    "--headless=new", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
]


def browser_or_skip():
    """Playwright's sync API, or a skip naming what is missing (a failure under CI=true: required there)."""
    missing = None
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        missing = "playwright is not installed (pip install -e '.[dev]')"
    if missing is None and not (os.path.isfile(CHROMIUM) and os.access(CHROMIUM, os.X_OK)):
        missing = f"no chromium at {CHROMIUM} (./run.sh setup installs it as root where apt is; or: apt-get install chromium)"
    if missing:
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true and the browser test cannot run: {missing}")
        pytest.skip(missing)
    return sync_playwright
