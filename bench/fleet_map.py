"""A screenshot of the fleet server's live map during the fleet demo: ``python -m bench.fleet_map``.

Runs ``cae_lcd.fleet.demo.run_demo`` (the same as ``make fleet-demo``) and, once the robots have streamed and while the
server still runs, opens ``/map#token=...`` in headless Chromium and saves the page as ``docs/fleet_map.png``
(PNG, maximum compression). Needs ``chromium`` on PATH (``apt-get install -y chromium``).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import subprocess
import tempfile
from pathlib import Path

import cv2

from cae_lcd.core.errors import LCDError
from cae_lcd.fleet.demo import run_demo

__all__ = ["main", "screenshot", "chromium_command"]

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO.parent / "shared" / "datasets" / "kitti"


def chromium_command(profile: str | Path, size: tuple[int, int] = (1000, 760), wait_ms: int = 8000) -> list[str]:
    """Headless Chromium's command line (add ``--screenshot=PNG`` or ``--dump-dom``, then the URL): a fresh
    profile, ``wait_ms`` of virtual time for the page's scripts and requests to settle.

    Raises:
        LCDError: no Chromium on PATH.
    """
    chromium = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if chromium is None:
        raise LCDError("no chromium on PATH (apt-get install -y chromium)")
    return [chromium, "--headless", "--no-sandbox", "--disable-gpu", f"--window-size={size[0]},{size[1]}",
            f"--virtual-time-budget={wait_ms}", f"--user-data-dir={profile}"]


def screenshot(url: str, path: Path, size: tuple[int, int] = (1000, 760), wait_ms: int = 8000) -> Path:
    """Saves a headless-Chromium screenshot of ``url`` as a PNG at ``path``.

    Raises:
        LCDError: no Chromium on PATH, or it wrote no picture.
    """
    with tempfile.TemporaryDirectory() as profile:
        raw = Path(profile) / "shot.png"
        subprocess.run(chromium_command(profile, size, wait_ms) + [f"--screenshot={raw}", url], capture_output=True,
                       timeout=180, check=False)
        image = cv2.imread(str(raw), cv2.IMREAD_COLOR)
    if image is None:
        raise LCDError(f"chromium wrote no screenshot of {url}")
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return path


def main(out: str | Path = "runs/bench/fleet_map", picture: str | Path = REPO / "docs" / "fleet_map.png",
         frames: int = 200) -> Path:
    """Runs the demo into ``out`` and saves the map's screenshot at ``picture``; returns its path."""
    def shoot(url: str, token: str) -> None:
        screenshot(f"{url}/map#token={token}", Path(picture))
        log.info("map screenshot: %s", picture)

    summary = run_demo(out, KITTI, frames=frames, while_serving=shoot)
    log.info("demo: merged %s, overlaps %d, B trajectory RMSE %.3f m", summary["merged"], len(summary["overlaps"]),
             summary.get("merged_b_rmse_m", float("nan")))
    return Path(picture)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/bench/fleet_map", help="the demo's output folder")
    ap.add_argument("--picture", default=str(REPO / "docs" / "fleet_map.png"), help="where the screenshot goes")
    ap.add_argument("--frames", type=int, default=200, help="first frames of KITTI 00 streamed")
    args = ap.parse_args()
    main(args.out, args.picture, args.frames)
