"""A screenshot of the Rerun viewer on a run's recording, at one frame (the README's docs/img/rerun_main_job.jpg).

Usage: ``.venv/bin/python scripts/rerun_screenshot.py <run dir>/run.rrd <image.jpg> [--frame N] [--size WxH]``

Starts the viewer of the installed rerun-sdk without a window (``rerun --headless``; it needs a
Vulkan driver, e.g. Mesa's software one: ``apt-get install mesa-vulkan-drivers``), opens the
recording with the run's own layout, moves the time cursor to the frame, and writes the screenshot
as a JPEG of the window's size. Nothing is downloaded.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2


def free_port() -> int:
    """A TCP port free on this machine now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> None:
    """Shoot the viewer on the recording at the frame asked for."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=Path)
    parser.add_argument("image", type=Path)
    parser.add_argument("--frame", type=int, default=None, help="the frame to show (default: the end of the run)")
    parser.add_argument("--size", default="1600x1000", help="the window's size in points")
    parser.add_argument("--settle", type=float, default=20.0, help="seconds to let the viewer draw before shooting")
    args = parser.parse_args()
    from rerun.experimental import ViewerClient

    port = free_port()
    rerun = Path(sys.executable).parent / "rerun"
    command = [str(rerun), "--headless", "--port", str(port), "--window-size", args.size, "--hide-welcome-screen"]
    # its own process group: the `rerun` script starts the viewer's binary as a child, which must end too
    viewer = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while True:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            if time.monotonic() > deadline or viewer.poll() is not None:
                sys.exit("the headless viewer did not start (is a Vulkan driver installed?)")
            time.sleep(0.5)
        client = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
        client.open(str(args.recording.resolve()))
        time.sleep(args.settle)  # the recording loads, then every view draws (a software renderer is slow)
        if args.frame is not None:
            client.set_time("frame", sequence=args.frame, play_state="paused")
            time.sleep(args.settle / 2)
        with tempfile.TemporaryDirectory() as tmp:
            shot = Path(tmp) / "shot.png"
            client.save_screenshot(str(shot))
            image = cv2.imread(str(shot))
            if image is None:
                sys.exit("the viewer wrote no screenshot")
    finally:
        os.killpg(viewer.pid, signal.SIGTERM)
        viewer.wait(timeout=30)
    width, height = map(int, args.size.split("x"))
    image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)  # it shoots at the display's scale
    cv2.imwrite(str(args.image), image, [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"{args.image}: {width} x {height}")


if __name__ == "__main__":
    main()
