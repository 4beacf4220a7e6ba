"""Screenshots of a results folder's viewer in headless Chromium (docs/viewer.md's images).

    python benchmarks/viewer_screenshots.py results/demo --view v005 --out docs/img/viewer [--page]

Writes ``<out>_<mode>.png`` of the canvas (relit, analyzer 0 and 90 degrees, AoLP, DoP, Mueller, maps, the free light,
the capture's cameras), and with ``--page`` one of the whole page with the value under the cursor.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

BROWSER_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]
SHOTS = (("relight", "{mode: 'relight', useAnalyzer: false}"),
         ("analyzer0", "{mode: 'relight', useAnalyzer: true, analyzer: 0}"),
         ("analyzer90", "{mode: 'relight', useAnalyzer: true, analyzer: 90}"),
         ("aolp", "{mode: 'aolp', useAnalyzer: false}"), ("dop", "{mode: 'dop'}"), ("mueller", "{mode: 'mueller'}"),
         ("eta", "{mode: 'map', map: 'eta'}"), ("rho_d", "{mode: 'map', map: 'rho_d'}"),
         ("sigma_s", "{mode: 'map', map: 'sigma_s'}"), ("cluster", "{mode: 'map', map: 'cluster'}"),
         ("normal", "{mode: 'map', map: 'normal'}"),
         ("free_light", None))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", type=Path)
    parser.add_argument("--view", default=None, help="captured view to snap to (default: the first)")
    parser.add_argument("--out", type=Path, required=True, help="prefix of the PNGs")
    parser.add_argument("--size", type=int, nargs=2, default=None, help="canvas pixels (default: the capture's x2)")
    parser.add_argument("--page", action="store_true", help="also the whole page, hovering the object's centre")
    parser.add_argument("--zoom", type=float, default=1.0, help="move the camera this many times closer")
    parser.add_argument("--dop-max", type=float, default=1.0, help="DoP shown full red at this value")
    args = parser.parse_args(argv)
    from playwright.sync_api import sync_playwright

    index = (args.results / "viewer" / "index.html").resolve()
    if not index.is_file():
        raise SystemExit(f"{index}: missing; run `sellip view {args.results}` first")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=shutil.which("chromium") or "/usr/bin/chromium", args=BROWSER_ARGS)
        page = browser.new_page(viewport={"width": 1500, "height": 1000}, device_scale_factor=1)
        page.goto(index.as_uri())
        page.wait_for_function("window.sellipViewer && (window.sellipViewer.ready || window.sellipViewer.error)",
                               timeout=300_000)
        meta = page.evaluate("window.sellipViewer.meta.intrinsics")
        width, height = args.size or (int(meta["width"]) * 2, int(meta["height"]) * 2)
        page.evaluate(f"window.sellipViewer.setSize({width}, {height})")
        if args.view:
            page.evaluate(f"window.sellipViewer.snapToView('{args.view}')")
        page.evaluate(f"window.sellipViewer.zoom({1 / args.zoom})")
        page.evaluate(f"window.sellipViewer.set({{dopMax: {args.dop_max}}})")
        exposure = page.evaluate("window.sellipViewer.meta.exposure") / args.zoom**2  # the flash came closer
        page.evaluate(f"window.sellipViewer.set({{exposure: {exposure}}})")
        for name, options in SHOTS:
            if options is None:  # the free light 50 degrees to the side of the camera and 20 above
                page.evaluate("window.sellipViewer.set({mode: 'relight', useAnalyzer: false})")
                page.evaluate("window.sellipViewer.freeLightFromCamera(0.9, 0.35)")
            else:
                page.evaluate(f"window.sellipViewer.set({options})")
            page.locator("#view").screenshot(path=f"{args.out}_{name}.png")
        page.evaluate("window.sellipViewer.set({mode: 'relight', light: 'flash', frusta: true})")
        if args.view:
            page.evaluate(f"window.sellipViewer.snapToView('{args.view}')")
        page.evaluate("window.sellipViewer.orbit(0, -100)")
        page.evaluate("window.sellipViewer.zoom(5)")
        page.locator("#view").screenshot(path=f"{args.out}_cameras.png")
        if args.page:
            page.evaluate("window.sellipViewer.set({frusta: false, mode: 'map', map: 'eta'})")
            if args.view:
                page.evaluate(f"window.sellipViewer.snapToView('{args.view}')")
            page.evaluate(f"window.sellipViewer.zoom({1 / args.zoom})")
            box = page.locator("#view").bounding_box()
            page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
            page.wait_for_timeout(600)
            page.screenshot(path=f"{args.out}_page.png")
        browser.close()
    print(f"wrote {args.out}_*.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
