"""The explorer page (pipeline/reporting/explorer.py) in a real headless browser, on synthetic
fronts (no training, no MuJoCo): strings from params and artifacts stay text.

Skips, saying why, where chromium or Playwright is missing (tests/support/browser.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from support.browser import open_browser

from pipeline.evaluation.render import mp4_bytes
from pipeline.reporting.explorer import explorer_html, script_json

HOSTILE = "<img src=x onerror=window.__pwned=1>"
BREAKOUT = '"></script><script>window.__pwned=2</script>'
QUOTED_DIR = 'it\'s a "dir" <b>&amp;'


def tiny_mp4(path: Path, shade: int) -> None:
    """A real 8-frame H.264 clip (a moving bar), so the browser has something to decode."""
    frames = np.full((8, 48, 64, 3), shade, np.uint8)
    for t in range(8):
        frames[t, :, 8 * t : 8 * t + 8] = 255 - shade
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(mp4_bytes(frames, 8, path))


def point(i: int, returns, origin="child", objective=None, policy_name=None, clip=None, export=None) -> dict:
    return {
        "id": i,
        "on_front": True,
        "origin": origin,
        "objective": objective,
        "policy_name": policy_name,
        "iteration": 0 if origin == "specialist" else i,
        "parents": [] if origin == "specialist" else [0, 1],
        "target_weight": None if origin == "specialist" else [0.5, 0.5],
        "returns": [float(x) for x in returns],
        "std": [1.0] * len(returns),
        "clip": clip,
        "export": export,
    }


def test_script_json_cannot_end_its_script_element():
    text = script_json({"s": "</script><!-- & \u2028\u2029 >"})
    assert "<" not in text and ">" not in text and "&" not in text
    assert "\u2028" not in text and "\u2029" not in text
    assert json.loads(text) == {"s": "</script><!-- & \u2028\u2029 >"}


@pytest.fixture
def hostile_page(tmp_path) -> Path:
    """A page whose every string from params or artifacts is an attack, with a real clip under a
    folder whose name holds quotes, spaces and markup."""
    clip_rel = f"clips/{QUOTED_DIR}/member_0002.mp4"
    tiny_mp4(tmp_path / clip_rel, 40)
    clip = {"mp4": clip_rel, "thumb": "thumbs/x.png", "returns": [3.0, 3.0], "episode_steps": 8, "frames": 8}
    clip["fps"] = 8
    points = [
        point(0, [10.0, 0.0], "specialist", 0, HOSTILE),
        point(1, [0.0, 10.0], BREAKOUT, None, None),
        point(2, [6.0, 6.0], "child", clip=clip, export=f'../export/{QUOTED_DIR}/javascript:alert(1) "x".pt'),
    ]
    panel = {"method": HOSTILE, "label": BREAKOUT, "colour": "#1f77b4", "seed": 0, "front": [1, 2, 0]}
    panel["points"] = points
    page = tmp_path / "explorer.html"
    page.write_text(explorer_html([panel], [HOSTILE, BREAKOUT], f"fronts {HOSTILE}"))
    return page


def test_hostile_names_and_paths_are_shown_as_text_and_run_nothing(hostile_page):
    with open_browser() as new_page:
        page, watched = new_page(hostile_page)
        page.wait_for_selector(".pt")
        # hover and click every point: the side table then shows each one's strings
        for k in range(page.locator(".pt").count()):
            page.locator(".pt").nth(k).dispatch_event("mouseenter")
            page.locator(".pt").nth(k).click(force=True)
            text = page.locator("#info").inner_text()
            assert HOSTILE in text and BREAKOUT in text, text
        assert page.evaluate("window.__pwned") is None
        assert page.evaluate("document.querySelectorAll('img, b, script').length") == 2  # the page's own scripts
        body = page.locator("body").inner_text()
        assert HOSTILE in body and BREAKOUT in body
        # the last point clicked is the child with the clip and the export path
        link = page.locator("#info a")
        assert link.inner_text() == f'../export/{QUOTED_DIR}/javascript:alert(1) "x".pt'
        href = link.get_attribute("href")
        assert not href.startswith("javascript") and ":" not in href, href
        # the clip under the quoted folder really plays
        page.wait_for_function("document.getElementById('clip').readyState >= 2", timeout=20_000)
        assert page.evaluate("document.getElementById('clip').error") is None
        assert page.evaluate("window.__pwned") is None
        assert not watched.dialogs and not watched.page_errors and not watched.console_errors, watched
        assert not watched.network(), watched.requests
