"""The README's picture of the explorer: open a render's explorer.html in headless Chromium (as a
user opens it, offline, from file://), pick one front policy so that its clip plays beside the
fronts, and save a screenshot. Run by hand after a render (needs `chromium` and the dev extra's
Playwright):

    python benchmarks/explorer_picture.py data/render/explorer.html docs/explorer.png --pick 0.5

--pick chooses the point by its place along the plot of one seed (--seed, default the first) among
one method's points (--method, default all; 0: the left end, 1: the right end); choose a seed and
method the render filmed (render.seeds, render.methods). The page and its clips are the render's, unchanged.
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
    ap.add_argument("--method", default=None, help="whose front's point to play (default: any method's)")
    ap.add_argument("--seed", type=int, default=None, help="the seed's plot to pick from (default: the first)")
    ap.add_argument(
        "--only", nargs="*", default=None, help="methods left shown (the others hidden with their legend buttons)"
    )
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
        if args.only is not None:
            for button in page.locator("#legend button[data-method]").all():
                if button.get_attribute("data-method") not in args.only:
                    button.click()
        section = (
            page.locator(f"section[data-seed='{args.seed}']")
            if args.seed is not None
            else page.locator("section").first
        )
        points = section.locator(f".pt[data-key^='{args.method}/']" if args.method else ".pt")
        n = points.count()
        if n == 0:
            print(f"error: {args.explorer}: no front points there (--seed, --method)", file=sys.stderr)
            return 1
        # the points in order along the first objective (left to right)
        xs = points.evaluate_all("ps => ps.map((p, i) => [p.getBoundingClientRect().x, i, p.dataset.key || ''])")
        xs.sort()
        _, index, key = xs[min(len(xs) - 1, max(0, round(args.pick * (len(xs) - 1))))]
        target = points.nth(index)
        section.scroll_into_view_if_needed()
        target.dispatch_event("mouseenter")
        target.click(force=True)
        page.wait_for_timeout(args.seconds * 1000)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(args.out), full_page=False)
        browser.close()
    print(f"{args.out}: the explorer with point {key or index} ({n} to pick from) playing")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
