"""``make demo``: generate the embedded synthetic sequence, run the default tracker on it, evaluate.

Usage: ``python -m surfelslam.tools.demo OUT_DIR``. Prints ATE and FPS; writes OUT_DIR/sequence (the
generated TUM-layout sequence) and OUT_DIR/run (trajectory, map, metrics, figures).
"""

from __future__ import annotations

import sys
from pathlib import Path

from rich.markup import escape

from surfelslam.datasets import DatasetOptions, open_sequence
from surfelslam.errors import SurfelSlamError
from surfelslam.tools.common import console, print_error

DEMO_SCENE = "room"
DEMO_TRAJECTORY = "handheld"
DEMO_FRAMES = 300
DEMO_SEED = 0
#: the files are 640x480; the trackers work on their unbiased 2x2 block means (``tracking.max_width_px``),
#: which is more accurate and faster than reading them with ``--downsample 2`` (every second pixel)
DEMO_DOWNSAMPLE = 1


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0] if argv else "out/demo")
    try:
        from surfelslam.api import run_sequence
        from surfelslam.synth.writer import generate_sequence
        from surfelslam.tools.run import print_summary

        seq_dir = out / "sequence"
        if not (seq_dir / "INFO.txt").is_file():
            console.print(f"[bold]1/3 synth[/]: {DEMO_FRAMES} frames of scene '{DEMO_SCENE}', "
                          f"'{DEMO_TRAJECTORY}' motion, Kinect-like noise -> {escape(str(seq_dir))}")
            generate_sequence(seq_dir, scene=DEMO_SCENE, style=DEMO_TRAJECTORY, n_frames=DEMO_FRAMES,
                              noise="kinect", seed=DEMO_SEED, width=640, height=480, progress=True)
        else:
            console.print(f"[bold]1/3 synth[/]: reusing {escape(str(seq_dir))}")
        seq = open_sequence(seq_dir, DatasetOptions(downsample=DEMO_DOWNSAMPLE))
        from surfelslam.slam import SlamConfig

        cfg = SlamConfig()
        console.print(f"[bold]2/3 run[/]: tracker '{cfg.tracker}' on {seq.intrinsics.width}x{seq.intrinsics.height} "
                      f"frames (tracked and fused at most {cfg.tracking.max_width_px} px wide)")
        run_dir = out / "run"
        metrics = run_sequence(seq, run_dir, cfg, progress=True, figures=True)
        print_summary(metrics, run_dir)
        console.print("[bold]3/3 eval[/]")
        ate_cm = metrics["eval"]["ate_rmse_m"] * 100 if "eval" in metrics else float("nan")
        console.print(f"ATE RMSE: {ate_cm:.2f} cm   FPS: {metrics['fps']:.1f}   outputs: {run_dir}", markup=False)
    except SurfelSlamError as exc:
        print_error(exc)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
