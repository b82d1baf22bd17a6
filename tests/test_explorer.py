"""The explorer page (pipeline/reporting/explorer.py) in a real headless browser, on synthetic
fronts (no training, no MuJoCo): strings from params and artifacts stay text.

Skips, saying why, where chromium or Playwright is missing (tests/support/browser.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support.browser import changes, open_browser
from support.fronts import point, preferred, synthetic_panels, tiny_mp4

from pipeline.reporting.explorer import explorer_html, script_json

HOSTILE = "<img src=x onerror=window.__pwned=1>"
BREAKOUT = '"></script><script>window.__pwned=2</script>'
QUOTED_DIR = 'it\'s a "dir" <b>&amp;'
EXPORT_NAME = f'{QUOTED_DIR}/javascript:alert(1) "x".pt'
METHODS = ["mapex_td3", "warmup_only_td3", "interpolate_td3"]


@pytest.fixture(scope="module")
def new_page():
    with open_browser() as opener:
        yield opener


# the first point node whose key ends with the given text (keys hold method names: no CSS selector)
NODE = "((end) => [...document.querySelectorAll('.pt')].find((e) => e.dataset.key.endsWith(end)))"


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
        point(2, [6.0, 6.0], "child", clip=clip, export=f"../export/{EXPORT_NAME}"),
    ]
    points[2]["export_file"] = f"data/export/{EXPORT_NAME}"
    points[1]["policy_name"] = HOSTILE
    panel = {"method": HOSTILE, "label": BREAKOUT, "colour": "#1f77b4", "seed": 0, "front": [1, 2, 0]}
    panel["points"] = points
    page = tmp_path / "explorer.html"
    page.write_text(explorer_html([panel], [HOSTILE, BREAKOUT], f"fronts {HOSTILE}"))
    return page


def test_hostile_names_and_paths_are_shown_as_text_and_run_nothing(hostile_page, new_page):
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
    # the child with the clip and the export path
    page.evaluate(f"{NODE}('/0/2').dispatchEvent(new MouseEvent('click'))")
    link = page.locator("#info a")
    assert link.inner_text() == f"data/export/{EXPORT_NAME}"
    href = link.get_attribute("href")
    assert not href.startswith("javascript") and ":" not in href, href
    assert (
        page.locator("#loadcode").inner_text()
        == f"import torch\npolicy = torch.jit.load({json.dumps(f'data/export/{EXPORT_NAME}')})"
    )
    # the clip under the quoted folder really plays
    page.wait_for_function("document.getElementById('clip').readyState >= 2", timeout=20_000)
    assert page.evaluate("document.getElementById('clip').error") is None
    assert page.evaluate("window.__pwned") is None
    assert not watched.dialogs and not watched.page_errors and not watched.console_errors, watched
    assert not watched.network(), watched.requests


# -- comparing methods: a synthetic front of three methods, two seeds ------------------------------


@pytest.fixture
def two_objective_page(tmp_path):
    panels = synthetic_panels(tmp_path, 2, METHODS, [0, 1])
    # a child exactly where seed 0's first starting policy of MAPEX-TD3 is: the star must stay on top
    first = panels[0]["points"][0]
    panels[0]["points"].append(point(99, first["returns"], clip=None))
    page = tmp_path / "explorer.html"
    page.write_text(explorer_html(panels, ["x-velocity", "energy"], "fronts"))
    return page, panels


def clip_advances(page) -> bool:
    """The side video has a clip, plays, and its time moves on."""
    page.wait_for_function(
        "(() => { const v = document.getElementById('clip'); return v.readyState >= 2 && !v.paused; })()"
    )
    t0 = page.evaluate("document.getElementById('clip').currentTime")
    # Polled, not a fixed pause: on a loaded machine the decoder may take longer than any one
    # pause to show the next frame, and a still clip must still fail (after support.browser.WAIT_MS).
    return changes(page, "document.getElementById('clip').currentTime", t0)


def test_one_plot_per_seed_with_every_method_ticks_and_names(two_objective_page, new_page):
    path, panels = two_objective_page
    page, watched = new_page(path)
    page.wait_for_selector(".pt")
    assert page.locator("section").count() == 2 and page.locator("svg.plot").count() == 2
    for seed in (0, 1):
        svg = page.locator(f"section[data-seed='{seed}'] svg.plot")
        for method in METHODS:
            want = sum(len(p["points"]) for p in panels if p["method"] == method and p["seed"] == seed)
            assert svg.locator(f".pt[data-method='{method}']").count() == want
        labels = svg.locator("text.axis").all_text_contents()
        assert labels == ["x-velocity", "energy"], labels
        for anchor in ("middle", "end"):  # the x axis's ticks, then the y axis's: at least 3 each, in order
            ticks = [float(t) for t in svg.locator(f"text.tick[text-anchor='{anchor}']").all_text_contents()]
            assert len(ticks) >= 3 and ticks == sorted(set(ticks)), (anchor, ticks)
        # stars come after every circle in their plot: drawn on top
        kinds = svg.locator(".pt").evaluate_all("(ns) => ns.map((n) => n.tagName)")
        assert kinds.index("polygon") > max(k for k, t in enumerate(kinds) if t == "circle")
    # the star under which a child lies is the element found at its centre: it can be hovered
    key = "mapex_td3/0/0"
    box = page.evaluate(
        f"(() => {{ const r = {NODE}('{key}').getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2]; }})()"
    )
    assert page.evaluate(f"document.elementFromPoint({box[0]}, {box[1]}).dataset.key") == key
    page.mouse.move(*box)
    assert page.locator("#info").get_attribute("data-key") == key
    # the legend hides a method's points and front line, and shows them again
    button = page.locator("#legend button[data-method='warmup_only_td3']")
    button.click()
    assert page.locator(".pt[data-method='warmup_only_td3']:visible").count() == 0
    assert page.locator(".pt[data-method='mapex_td3']:visible").count() > 0
    assert page.locator("polyline[data-method='warmup_only_td3']:visible").count() == 0
    button.click()
    assert page.locator(".pt[data-method='warmup_only_td3']:visible").count() > 0
    assert not watched.network() and not watched.console_errors and not watched.page_errors, watched


def filmed_child(panels, method: str, seed: int) -> tuple[str, str]:
    """The key of a front child of `method`, `seed` and its clip's path."""
    panel = next(p for p in panels if p["method"] == method and p["seed"] == seed)
    p = next(p for p in panel["points"] if p["origin"] == "child" and p["clip"])
    return f"{method}/{seed}/{p['id']}", p["clip"]["mp4"]


def playing(page) -> str:
    """The path the side video plays, once it has one."""
    return page.wait_for_function("document.getElementById('clip').currentSrc").json_value()


def test_hover_and_click_play_the_clip(two_objective_page, new_page):
    path, panels = two_objective_page
    hovered, hovered_clip = filmed_child(panels, "warmup_only_td3", 1)
    clicked, clicked_clip = filmed_child(panels, "interpolate_td3", 0)
    page, watched = new_page(path)
    page.wait_for_selector(".pt")
    page.dispatch_event(f".pt[data-key='{hovered}']", "mouseenter")
    assert playing(page).endswith(hovered_clip)
    assert clip_advances(page)
    page.click(f".pt[data-key='{clicked}']", force=True)
    assert page.locator("#info").get_attribute("data-key") == clicked
    # a click keeps its point: hovering another does not replace it
    page.dispatch_event(f".pt[data-key='{hovered}']", "mouseenter")
    assert page.locator("#info").get_attribute("data-key") == clicked
    assert playing(page).endswith(clicked_clip)
    assert clip_advances(page)
    method, seed, i = clicked.split("/")
    assert f"data/export/{method}/seed{seed}/member_{int(i):04d}.pt" in page.locator("#loadcode").inner_text()
    assert not watched.network() and not watched.console_errors and not watched.page_errors, watched


@pytest.mark.parametrize("weights", [(1.0, 0.0), (0.0, 1.0), (0.6, 0.4), (0.25, 0.75)])
def test_the_preference_picks_what_numpy_picks_and_plays_it(two_objective_page, weights, new_page):
    path, panels = two_objective_page
    page, watched = new_page(path)
    page.wait_for_selector(".pt")
    for m, w in enumerate(weights):
        page.locator("input.weight").nth(m).fill(f"{w:g}")
    want = preferred(panels, weights)
    assert page.locator("#picked").get_attribute("data-key") == want
    assert page.locator("#info").get_attribute("data-key") == want
    method, seed, i = want.split("/")
    assert playing(page).endswith(f"clips/{method}/seed{seed}/member_{int(i):04d}.mp4")
    assert clip_advances(page)
    assert page.locator(f".pt.pick[data-key='{want}']").count() == 1
    # hiding the winner's method picks among the others, as numpy does without it
    page.locator(f"#legend button[data-method='{method}']").click()
    assert page.locator("#picked").get_attribute("data-key") == preferred(panels, weights, hidden=(method,))
    assert not watched.network() and not watched.console_errors and not watched.page_errors, watched


def test_three_objectives_pairwise_projections_and_a_turning_3d_view(tmp_path, new_page):
    names = ["x-velocity", "energy", "height"]
    panels = synthetic_panels(tmp_path, 3, METHODS, [0])
    path = tmp_path / "explorer.html"
    path.write_text(explorer_html(panels, names, "fronts"))
    page, watched = new_page(path)
    page.wait_for_selector(".pt")
    pairs = page.locator("svg.plot[data-pair]").evaluate_all("(ns) => ns.map((n) => n.dataset.pair)")
    assert pairs == ["0-1", "0-2", "1-2"]
    view = page.locator("svg.view3d")
    assert view.count() == 1
    assert sorted(view.locator("text.axis").all_text_contents()) == sorted(names)
    n_points = sum(len(p["points"]) for p in panels)
    assert view.locator(".pt").count() == n_points
    where = "[...document.querySelectorAll('svg.view3d circle.pt')].map((n) => n.getAttribute('cx')).join()"
    assert changes(page, where, page.evaluate(where)), "the 3-D view does not turn"
    weights = (0.2, 0.3, 0.5)
    for m, w in enumerate(weights):
        page.locator("input.weight").nth(m).fill(f"{w:g}")
    assert page.locator("#picked").get_attribute("data-key") == preferred(panels, weights)
    assert view.locator(".pt.pick").count() == 1
    assert not watched.network() and not watched.console_errors and not watched.page_errors, watched
