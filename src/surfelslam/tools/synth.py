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
        scene: Annotated[str, typer.Option(
            "--scene", help="Scene: room, office, plane, corridor or floor (rooms of different sizes along a "
                            "corridor, joined by doorways).")] = "room",
        texture: Annotated[str, typer.Option(
            "--texture", help="rich (texture everywhere) or plain (flat painted walls, fabric and cabinets; "
                              "texture only on wood, books and posters, as in real rooms).")] = "rich",
        frames: Annotated[int, typer.Option("--frames", help="Number of frames.")] = 300,
        noise: Annotated[str, typer.Option(
            "--noise", help="kinect (Kinect-v1-like), kinect-distorted (the same with a fixed low-frequency depth "
                            "distortion), icl (ICL-NUIM's synthetic noise: jittered, quantised disparity, no holes) "
                            "or none (exact).")] = "kinect",
        seed: Annotated[int, typer.Option("--seed", help="Seed of textures, motion jitter and noise.")] = 0,
        trajectory: Annotated[
            str, typer.Option("--trajectory", help="Motion: slow, fast, handheld, loop, upward (ceiling, one "
                                                   "wall), tour (slow with an upward stretch), tour-across (the "
                                                   "tour looking across the room: far views) or "
                                                   "walk (floor only: walking at ~1.2 m/s through the corridor "
                                                   "and into every room, laps repeating).")
        ] = "slow",
        width: Annotated[int, typer.Option("--width", help="Image width (intrinsics scaled from 640).")] = 640,
        height: Annotated[int, typer.Option("--height", help="Image height (intrinsics scaled from 480).")] = 480,
        fps: Annotated[float, typer.Option("--fps", help="Frame rate (timestamps are index / fps).")] = 30.0,
        motion: Annotated[Path | None, typer.Option(
            "--motion", help="Replay a recorded camera motion instead of --trajectory: a TUM trajectory file "
                             "('timestamp tx ty tz qx qy qz qw', e.g. a dataset's groundtruth.txt: real hand-held "
                             "motion). Its motion relative to its first pose is placed in the scene's free space.")
        ] = None,
        speed: Annotated[float, typer.Option(
            "--speed", help="--motion: replay at this many times the recorded speed (3 = the same motion at 3x).")
        ] = 1.0,
        motion_start: Annotated[float, typer.Option(
            "--motion-start", help="--motion: start this many seconds after the recording's first pose.")] = 0.0,
        colour_offset_ms: Annotated[float, typer.Option(
            "--colour-offset-ms", help="Take each frame's colour this many ms after its depth (negative: before), "
                                       "as a sensor without colour/depth sync (TUM's Kinect: up to 20 ms); "
                                       "rgb.txt gets the colour stamps, ground truth is at the depth stamps.")
        ] = 0.0,
        colour_jitter_ms: Annotated[float, typer.Option(
            "--colour-jitter-ms", help="Add a uniform random +-this many ms to each frame's colour offset.")] = 0.0,
        progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
    ) -> None:
        """Render a textured indoor scene along a camera trajectory; write rgb/, depth/, groundtruth.txt."""
        from surfelslam.io.trajectory import read_tum
        from surfelslam.synth.writer import generate_sequence

        recorded = None if motion is None else read_tum(motion)
        path = generate_sequence(
            out, scene=scene, style=trajectory, n_frames=frames, noise=noise, seed=seed,
            width=width, height=height, fps=fps, progress=progress, motion=recorded, speed=speed,
            motion_start_s=motion_start, motion_label=str(motion), texture=texture,
            colour_offset_s=colour_offset_ms / 1000.0, colour_jitter_s=colour_jitter_ms / 1000.0,
        )
        what = trajectory if motion is None else f"motion of {motion} at {speed:g}x"
        console.print(f"wrote {frames} frames ({scene}, {texture} texture, {what}, noise {noise}, seed {seed}) "
                      f"to {path}", markup=False)
