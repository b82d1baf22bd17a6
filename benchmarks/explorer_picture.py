"""The README's picture of the explorer: open a render's explorer.html in headless Chromium (as a
user opens it, offline, from file://), pick one front policy so that its clip plays beside the
fronts, and save a screenshot. Run by hand after a render (needs `chromium` and the dev extra's
Playwright):

    python benchmarks/explorer_picture.py data/render/explorer.html docs/explorer.png --pick 0.5

--pick chooses the point by its place along a method's front of the first seed (--method, default
the first drawn; 0: the left end, 1: the right end). The page and its clips are the render's, unchanged.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("explorer", type=Path, help="a render's explorer.html")
    ap.add_argument("out", type=Path, help="PNG to write")
    ap.add_argument("--pick", type=float, default=0.5, help="which point of the first front to play (0..1)")
    ap.add_argument("--method", default=None, help="whose front's point to play (default: the first drawn)")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=820)
    ap.add_argument("--seconds", type=float, default=3.0, help="how long the clip plays before the shot")
    args = ap.parse_args()
    if not args.explorer.is_file():
        print(f"error: {args.explorer}: no such file (run the render stage first)", file=sys.stderr)
        return 2
    exe = next((found for name in CHROMIUM_NAMES if (found := shutil.which(name))), None)
    if exe is None:
        print("error: no chromium on PATH (apt-get install chromium)", file=sys.stderr)
        return 2
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=exe, args=["--autoplay-policy=no-user-gesture-required", "--disable-gpu"]
        )
        page = browser.new_context(offline=True, viewport={"width": args.width, "height": args.height}).new_page()
        page.goto(args.explorer.resolve().as_uri())
        page.wait_for_load_state("load")
        points = page.locator("section").first.locator(".pt")
        n = points.count()
        if n == 0:
            print(f"error: {args.explorer}: the page shows no front points", file=sys.stderr)
            return 1
        # the points of the first method, ordered along the first objective
        xs = points.evaluate_all("ps => ps.map(p => [p.getBoundingClientRect().x, p.dataset.key || ''])")
        first = f"{args.method}/0" if args.method else (xs[0][1].rsplit("/", 1)[0] if "/" in xs[0][1] else None)
        chosen = [(x, k) for x, k in xs if first is None or k.startswith(first + "/")] or xs
        chosen.sort()
        x, key = chosen[min(len(chosen) - 1, max(0, round(args.pick * (len(chosen) - 1))))]
        target = points.nth([k for _, k in xs].index(key)) if key else points.nth(0)
        target.dispatch_event("mouseenter")
        target.click(force=True)
        page.wait_for_timeout(args.seconds * 1000)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(args.out), full_page=False)
        browser.close()
    print(f"{args.out}: the explorer with point {key or 0} of {n} playing")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
