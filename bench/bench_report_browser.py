"""The HTML report with episode clips, opened in a real browser: headless Chromium (Debian's ``chromium`` package:
``apt-get install -y chromium``) loads a report whose gallery embeds MP4 clips (:mod:`tsnav.eval.video`).

Measured and printed (without Chromium installed, the report's figures only, and a line saying so):

* the report: seconds to write it, clips embedded, their size in bytes and frames per clip;
* the browser's decoding of a clip (a probe page beside the report, the only page with a script): ``readyState``,
  the video's size and duration as Chromium reads them, whether it can play H.264 in MP4, and the mean colour of
  the decoded frame at 1 s drawn into a canvas (not black: the frames were decoded);
* a screenshot of the report's gallery (``--screenshot``, default ``OUT/report_gallery.png``), to be looked at.

Without ``--from`` it builds the ``tiny-real`` world (three real iTHOR bathrooms at 128x128, about ten seconds)
into ``OUT/world``, evaluates the scripted explorer there with ``tsnav eval --video 2`` and reports that; with
``--from DIR`` it reports the evaluations under DIR instead (the report goes to OUT/report); with ``--index PAGE``
(e.g. ``out/demo/report/index.html``, the demo's own report) it opens that page as it is.

    .venv/bin/python bench/bench_report_browser.py [--out /tmp/report_bench] [--from DIR | --index PAGE]
                                                   [--screenshot PNG] [--anchor gallery]
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from tsnav.cli import main as tsnav
from tsnav.eval.video import read_clip
from tsnav.report.html import build_report

FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--allow-file-access-from-files",
    "--mute-audio",
    "--autoplay-policy=no-user-gesture-required",
]

PROBE = """<!doctype html><html><body><video id="v" src="{src}" muted preload="auto" width="512" height="320"></video>
<canvas id="c" width="512" height="320"></canvas><pre id="out">pending</pre><script>
const v = document.getElementById('v'), out = document.getElementById('out');
const h264 = v.canPlayType('video/mp4; codecs="avc1.42E01E"');
v.addEventListener('loadeddata', () => {{ v.currentTime = Math.min(1.0, v.duration / 2); }});
v.addEventListener('seeked', () => {{
  const c = document.getElementById('c').getContext('2d');
  c.drawImage(v, 0, 0, 512, 320);
  let mean = null;
  try {{ const d = c.getImageData(0, 0, 512, 320).data; let s = [0, 0, 0];
         for (let i = 0; i < d.length; i += 4) {{ s[0] += d[i]; s[1] += d[i + 1]; s[2] += d[i + 2]; }}
         mean = s.map(x => Math.round(x / (d.length / 4))); }} catch (e) {{ mean = String(e); }}
  out.textContent = JSON.stringify({{readyState: v.readyState, width: v.videoWidth, height: v.videoHeight,
                                    duration: v.duration, time: v.currentTime, h264: h264, mean_rgb: mean}});
}});
v.addEventListener('error', () => {{ out.textContent = JSON.stringify({{error: v.error && v.error.code, h264: h264}}); }});
</script></body></html>
"""


def chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def run_browser(args: list[str], timeout: float = 120) -> tuple[str, float]:
    """One headless Chromium run with a fresh profile: (stdout, seconds)."""
    profile = tempfile.mkdtemp(prefix="chromium-profile-")
    t0 = time.perf_counter()
    try:
        res = subprocess.run(
            [chromium(), *FLAGS, f"--user-data-dir={profile}", *args], capture_output=True, text=True, timeout=timeout
        )
    finally:
        shutil.rmtree(profile, ignore_errors=True)
    return res.stdout, time.perf_counter() - t0


def probe_clip(page: Path, tries: int = 3) -> tuple[dict, float, int]:
    """The probe page's result (Chromium's reading of the clip), seconds of the last run, and the runs it took (a
    cold first start on a loaded machine has been seen to end before the page ran)."""
    for k in range(1, tries + 1):
        dom, sec = run_browser(["--virtual-time-budget=15000", "--dump-dom", page.as_uri()])
        found = re.search(r'<pre id="out">(.*?)</pre>', dom, re.S)
        if found and found.group(1).startswith("{"):
            return json.loads(found.group(1)), sec, k
    return {"dom_tail": dom[-200:]}, sec, tries


def screenshot(url: str, shot: Path, window: str, tries: int = 3) -> tuple[np.ndarray, float, int]:
    """A screenshot of ``url`` (pixels, seconds of the last run, runs it took: a blank one is taken again)."""
    for k in range(1, tries + 1):
        _, sec = run_browser([f"--window-size={window}", "--virtual-time-budget=8000", f"--screenshot={shot}", url])
        img = np.asarray(Image.open(shot).convert("RGB")) if shot.exists() else np.zeros((1, 1, 3), np.uint8)
        if len(np.unique(img.reshape(-1, 3), axis=0)) > 16:
            break
    return img, sec, k


def make_evaluation(out: Path) -> Path:
    """The tiny-real world and an explorer evaluation with two clips; returns the folder to report."""
    from tsnav.world.build import build_dataset

    world, work = out / "world", out / "work"
    t0 = time.perf_counter()
    build_dataset(world, "tiny-real", workers=1, progress=False)
    print(f"world tiny-real: {time.perf_counter() - t0:.1f} s")
    episodes = work / "episodes.json"
    assert (
        tsnav(["episodes", "--data", str(world), "--split", "test", "--per-room-type", "12", "--out", str(episodes)])
        == 0
    )
    t0 = time.perf_counter()
    assert (
        tsnav(
            [
                "eval",
                "--data",
                str(world),
                "--episodes",
                str(episodes),
                "--policy",
                "explorer",
                "--out",
                str(work / "explorer"),
                "--video",
                "2",
            ]
        )
        == 0
    )
    print(f"tsnav eval --video 2: {time.perf_counter() - t0:.1f} s")
    return work


def main() -> None:
    ap = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="/tmp/report_bench", help="working folder (default /tmp/report_bench)")
    ap.add_argument("--from", dest="src", default=None, help="report the evaluations under this folder instead")
    ap.add_argument("--index", default=None, help="open this report page as it is (no evaluation, no report made)")
    ap.add_argument("--screenshot", default=None, help="PNG of the gallery (default OUT/report_gallery.png)")
    ap.add_argument("--anchor", default="gallery", help="section the screenshot scrolls to (default gallery)")
    ap.add_argument("--window", default="1320,1500", help="browser window WIDTH,HEIGHT (default 1320,1500)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.index:
        index = Path(args.index).resolve()
        made = ""
    else:
        root = Path(args.src) if args.src else make_evaluation(out)
        t0 = time.perf_counter()
        index = build_report(root, out / "report", gallery=3, video=2)
        made = f" in {time.perf_counter() - t0:.1f} s"
    html = index.read_text()
    clips = re.findall(r"<video src='([^']+)'", html)
    print(f"report: {index}{made}; {len(clips)} clips embedded")
    for c in clips:
        p = index.parent / c
        print(f"    {c}: {p.stat().st_size:,} bytes, {len(read_clip(p))} frames")
    if not clips:
        raise SystemExit("no clip in the report")

    if chromium() is None:
        print("no Chromium here (apt-get update && apt-get install -y chromium): the browser's measurements skipped")
        return
    probe = index.parent / "probe.html"
    probe.write_text(PROBE.format(src=clips[0]))
    result, sec, runs = probe_clip(probe)
    print(f"chromium ({sec:.1f} s, run {runs}) decoded {clips[0]}: {json.dumps(result)}")
    probe.unlink()

    shot = Path(args.screenshot) if args.screenshot else out / "report_gallery.png"
    img, sec, runs = screenshot(index.as_uri() + (f"#{args.anchor}" if args.anchor else ""), shot, args.window)
    print(
        f"chromium ({sec:.1f} s, run {runs}) screenshot {shot}: {img.shape[1]}x{img.shape[0]} px, "
        f"{len(np.unique(img.reshape(-1, 3), axis=0)):,} colours"
    )


if __name__ == "__main__":
    main()
