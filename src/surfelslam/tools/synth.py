"""``surfelslam synth OUT``: render a synthetic RGB-D sequence with exact ground truth (TUM layout)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from surfelslam.tools.common import console, handle_errors


def register(app: typer.Typer) -> None:
    @app.command("synth")
    @handle_errors
    def synth(
        out: Annotated[Path, typer.Argument(help="Output folder (created; existing frames are overwritten).")],
        scene: Annotated[str, typer.Option("--scene", help="Scene: room, office or plane.")] = "room",
        frames: Annotated[int, typer.Option("--frames", help="Number of frames.")] = 300,
        noise: Annotated[str, typer.Option("--noise", help="kinect (Kinect-v1-like) or none (exact).")] = "kinect",
        seed: Annotated[int, typer.Option("--seed", help="Seed of textures, motion jitter and noise.")] = 0,
        trajectory: Annotated[
            str, typer.Option("--trajectory", help="Motion: slow, fast, handheld or loop.")
        ] = "slow",
        width: Annotated[int, typer.Option("--width", help="Image width (intrinsics scaled from 640).")] = 640,
        height: Annotated[int, typer.Option("--height", help="Image height (intrinsics scaled from 480).")] = 480,
        fps: Annotated[float, typer.Option("--fps", help="Frame rate (timestamps are index / fps).")] = 30.0,
    ) -> None:
        """Render a textured indoor scene along a camera trajectory; write rgb/, depth/, groundtruth.txt."""
        from surfelslam.synth.writer import generate_sequence

        path = generate_sequence(
            out, scene=scene, style=trajectory, n_frames=frames, noise=noise, seed=seed,
            width=width, height=height, fps=fps, progress=True,
        )
        console.print(f"wrote {frames} frames ({scene}, {trajectory}, noise {noise}, seed {seed}) to {path}")
