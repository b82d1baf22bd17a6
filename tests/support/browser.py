"""A page opened in headless Chromium through Playwright, as a user opens explorer.html: from
file://, offline, with everything it asks of the network, the console and the dialogs recorded.

Debian's chromium is driven (`executable_path`), so Playwright downloads no browser. Tests skip,
saying why, where Playwright or chromium is missing (`make test` installs both).
"""

from __future__ import annotations

import shutil
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import pytest

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")
# How long `changes` waits for a page value to move: generous, since a loaded machine can stall a
# headless decoder or animation for seconds; a page that never moves still fails, after this.
WAIT_MS = 15_000


def chromium() -> str | None:
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


@dataclass
class Watched:
    """What a page did besides drawing: every request's URL, console errors, uncaught errors, dialogs."""

    requests: list[str] = field(default_factory=list)
    console_errors: list[str] = field(default_factory=list)
    page_errors: list[str] = field(default_factory=list)
    dialogs: list[str] = field(default_factory=list)

    def network(self) -> list[str]:
        """The requests that left the machine's files (anything but file:, data: and blob:)."""
        return [u for u in self.requests if not u.startswith(("file:", "data:", "blob:"))]


@contextmanager
def open_browser(width: int = 1280, height: int = 900):
    """Yields `new_page(path) -> (page, Watched)`, which closes the page it opened before; skips
    the test where the tools are missing."""
    exe = chromium()
    if exe is None:
        pytest.skip("no chromium: apt-get install chromium (make test installs it when run as root)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("no playwright: pip install -e '.[dev]'")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=exe,
            args=["--autoplay-policy=no-user-gesture-required", "--disable-gpu", "--disable-background-networking"],
        )
        context = browser.new_context(offline=True, viewport={"width": width, "height": height})

        opened = []

        def new_page(path: Path):
            while opened:  # one page at a time: an earlier test's clip stops playing
                opened.pop().close()
            watched = Watched()
            page = context.new_page()
            opened.append(page)
            page.on("request", lambda r: watched.requests.append(r.url))
            page.on("console", lambda m: watched.console_errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: watched.page_errors.append(str(e)))

            def on_dialog(dialog) -> None:
                watched.dialogs.append(f"{dialog.type}: {dialog.message}")
                dialog.dismiss()

            page.on("dialog", on_dialog)
            page.goto(path.resolve().as_uri())
            page.wait_for_load_state("load")
            return page, watched

        try:
            yield new_page
        finally:
            context.close()
            browser.close()


def changes(page, expression: str, before) -> bool:
    """Whether the page's JavaScript `expression` comes to differ from `before` within WAIT_MS
    (polled every animation frame): a clip's time moving on, a turning view's coordinates."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        page.wait_for_function(f"(before) => ({expression}) !== before", arg=before, timeout=WAIT_MS)
    except PlaywrightTimeout:
        return False
    return True
