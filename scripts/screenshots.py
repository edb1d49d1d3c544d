"""Pictures of a result folder as a user first meets it: the Rerun viewer's opening view and the report's first screen.

Usage: ``python scripts/screenshots.py OUT_DIR [--to DIR] [--size 1280x900]`` writes DIR/viewer.png and
DIR/report.png (DIR defaults to OUT_DIR). The viewer runs headless (Rerun's viewer control API; a software
rasterizer such as Mesa's lavapipe is enough), opens OUT_DIR/recording.rrd and moves its time cursor to
summary.json's opening frame, as ``batgraph view`` does. The report is drawn by a headless Chromium
(``chromium``, ``chromium-browser`` or ``google-chrome`` on PATH); it is skipped, with a line, without one.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path

from batgraph import viewer


def viewer_png(out_dir: Path, png: Path) -> None:
    """The headless viewer's screenshot of OUT_DIR/recording.rrd on its opening frame."""
    from rerun.experimental import ViewerClient

    port = viewer._free_port()
    client = ViewerClient.spawn(headless=True, port=port, executable_path=viewer._rerun_executable(),
                                hide_welcome_screen=True)
    try:
        client.open(str((out_dir / viewer.RECORDING_NAME).resolve()))
        frame = viewer._opening_frame_beside(out_dir / viewer.RECORDING_NAME)
        if frame is not None and not viewer.move_cursor(port, frame):
            print(f"{out_dir}: could not move the cursor to frame {frame}", file=sys.stderr)
        time.sleep(1.5)  # a few frames drawn after the cursor moved
        client.save_screenshot(str(png.resolve()))
    finally:
        client.quit()


def report_png(out_dir: Path, png: Path, size: str) -> bool:
    """Headless Chromium's screenshot of OUT_DIR/report.html at ``size`` (WxH); False without a Chromium."""
    exe = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
    if exe is None:
        return False
    subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--screenshot={png.resolve()}", f"--window-size={size.replace('x', ',')}",
                    (out_dir / "report.html").resolve().as_uri()], check=True, capture_output=True, timeout=120)
    return True


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out_dir", type=Path, help="a reconstruct output folder")
    p.add_argument("--to", type=Path, help="folder for viewer.png and report.png (default OUT_DIR)")
    p.add_argument("--size", default="1280x900", help="the report's window, WxH px (default 1280x900)")
    args = p.parse_args(argv)
    to = args.to or args.out_dir
    to.mkdir(parents=True, exist_ok=True)
    viewer_png(args.out_dir, to / "viewer.png")
    print(f"wrote {to / 'viewer.png'}")
    if report_png(args.out_dir, to / "report.png", args.size):
        print(f"wrote {to / 'report.png'}")
    else:
        print("no chromium on PATH: report.png not drawn", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
