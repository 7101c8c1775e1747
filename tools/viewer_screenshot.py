"""A screenshot of pipeline-view in the system's headless Chromium (the README's picture).

    .venv/bin/python tools/viewer_screenshot.py outputs/demo/jobs/<gopre hash> reports/viewer.png \\
        --start 200 --width 120

Serves SOURCE on a free loopback port, opens it at 1280x800, optionally types a goal sector into
the GUI and presses "Score next view", then saves the page. Needs Chromium (`make e2e` installs it)
and playwright (the dev extra).
"""

from __future__ import annotations

import argparse
import shutil
import socket
import sys
import time

from playwright.sync_api import sync_playwright

from pipeline.cli.view import start

ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--enable-unsafe-swiftshader"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source")
    parser.add_argument("out")
    parser.add_argument("--start", type=float, help="goal sector start (deg): type it and score")
    parser.add_argument("--width", type=float, default=120.0)
    args = parser.parse_args()
    browser_path = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser_path is None:
        print("no Chromium: run `make e2e` once (it installs the system package)", file=sys.stderr)
        return 1
    server, viewer = start(args.source, port=free_port())
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=browser_path, headless=True, args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(f"http://127.0.0.1:{server.get_port()}/")
            page.wait_for_function("document.body.innerText.includes('selected (pick order)')", timeout=60_000)
            if args.start is not None:
                for label, value in (("Start angle (deg)", args.start), ("Width (deg)", args.width)):
                    page.get_by_label(label).fill(str(value))
                    page.get_by_label(label).press("Enter")
                page.get_by_role("button", name="Score next view").click()
                page.wait_for_function("document.body.innerText.includes('Next best view')", timeout=120_000)
            for close in page.locator("button.mantine-Notification-closeButton").all():
                close.click()  # the "software WebGL" notice of a headless browser
            time.sleep(3)
            page.screenshot(path=args.out)
            browser.close()
    finally:
        server.stop()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
