"""`agentdress lab page-shots`: `make run` as a person sees it - the node on the shipped databases, the demo walk
with its shape sweep and the viewer - in headless Chromium (software WebGL), screenshots a few seconds apart and a
contact sheet of them (PNG). What the viewer's-eye counts of `agentdress bench look` can miss shows here: a body
drawn in another pose than its garments, cloth through cloth, jagged edges.
"""
from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
from pathlib import Path

from ..ros.harness import ChildProcess, random_domain, ros_env
from .look import LookSession, find_chromium



def contact_sheet(paths, out: Path, crop=(250, 80, 850, 1080), tile=(300, 500), columns: int = 4) -> Path:
    """The screenshots `paths`, each cropped to the agent and scaled to `tile`, in rows of `columns` (PNG, 128
    colours)."""
    from PIL import Image

    rows = -(-len(paths) // columns)
    sheet = Image.new("RGB", (tile[0] * columns, tile[1] * rows))
    for i, path in enumerate(paths):
        image = Image.open(path).convert("RGB").crop(crop).resize(tile)
        sheet.paste(image, ((i % columns) * tile[0], (i // columns) * tile[1]))
    sheet.quantize(128).save(out, optimize=True)
    return out


def take(folder: Path, shots: int = 8, gap_ms: int = 700, run_args=(), chromium: str | None = None) -> list[Path]:
    """`shots` screenshots (1100 x 1100) of the page of `agentdress run` into folder/page_NN.png."""
    from playwright.sync_api import sync_playwright

    chromium = chromium or find_chromium()
    folder.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="agentdress_shots_"))
    env = ros_env(random_domain(), str(work / "ros_log"))
    env["XDG_CONFIG_HOME"] = str(work / "config")
    run = ChildProcess([sys.executable, "-m", "agentdress_ros.ros.run_all", "--port", "0", *run_args], env,
                       work / "run.log")
    paths = []
    try:
        if not run.wait_for_output("open https://", 120):
            raise RuntimeError(f"the viewer printed no URL:\n{run.output()[-3000:]}")
        url = re.search(r"open (https://\S+)", run.output()).group(1)
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=chromium, headless=True, args=LookSession.BROWSER_ARGS)
            page = browser.new_context(ignore_https_errors=True, viewport={"width": 1100, "height": 1100}).new_page()
            page.goto(url)
            page.wait_for_function("() => agentdress.framesReceived > 30", timeout=120_000)
            page.wait_for_timeout(2000)
            for i in range(shots):
                paths.append(folder / f"page_{i:02d}.png")
                page.screenshot(path=str(paths[-1]), timeout=180_000)
                page.wait_for_timeout(gap_ms)
            browser.close()
    finally:
        run.stop(grace=60.0)
        shutil.rmtree(work, ignore_errors=True)
    return paths


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress lab page-shots", description=__doc__)
    parser.add_argument("--out", default="out/page_shots", help="folder of the screenshots")
    parser.add_argument("--shots", type=int, default=8)
    parser.add_argument("--sheet", default=None, help="also a contact sheet PNG here")
    parser.add_argument("run_args", nargs="*", help="passed to `agentdress run` (after --), e.g. --shape-sweep 0")
    args = parser.parse_args(argv)
    paths = take(Path(args.out), args.shots, run_args=args.run_args)
    if args.sheet:
        print(contact_sheet(paths, Path(args.sheet)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
