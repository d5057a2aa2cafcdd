"""``python -m surfelslam.warmup [PARTS]``: compile (or load from numba's on-disk cache) the JIT kernels ahead of a
session, in parts.

numba compiles a kernel on its first call and caches it beside the source. A fresh checkout has no cache, and
processes that start together (test workers, batch jobs) would each compile the same kernels. Warming up first, one
process per part running at the same time, compiles each kernel once (``make warmup``)::

    python -m surfelslam.warmup dense & python -m surfelslam.warmup outputs & python -m surfelslam.warmup sparse shape
    wait

The trackers' parts (``dense``, ``shape``, ``sparse``, ``parallel``) and what each tracker compiles are
:mod:`surfelslam.slam.warmup`'s; this entry adds ``outputs``: the map figures' splat renderer and the mesh's TSDF
and marching cubes (``viz/`` is above the trackers).
"""

from __future__ import annotations

import sys

import numpy as np

from surfelslam.slam import warmup as tracker_warmup

_OUTPUT_INTR = (60.0, 60.0, 31.5, 23.5, 64, 48)  # fx, fy, cx, cy, width, height: numba compiles types, not sizes


def _outputs() -> None:
    """The figures' splat renderer and the mesh's TSDF and marching cubes."""
    from surfelslam.mapping.mesh import TsdfVolume
    from surfelslam.types import Intrinsics
    from surfelslam.viz.map_figures import ViewCamera, render

    intr = Intrinsics(*_OUTPUT_INTR)
    v, u = np.mgrid[0:intr.height, 0:intr.width].astype(np.float32)
    depth = (1.0 + 0.004 * u + 0.002 * v).astype(np.float32)
    vol = TsdfVolume(0.02, 0.08, initial_blocks=1)  # room for one block: the volume grows, so rehash compiles too
    vol.integrate(depth, np.zeros((intr.height, intr.width, 3), np.uint8), intr, np.eye(4))
    mesh = vol.extract_mesh()
    cam = ViewCamera(np.eye(3), np.zeros(3), intr.width, intr.height, intr.cx, intr.cy, f_px=intr.fx)
    render(cam, mesh.vertices, mesh.normals, np.full(len(mesh.vertices), 0.01, np.float32))


_TRACKER_PARTS = tracker_warmup.PARTS
#: every part, in the order :func:`warm` runs them all
PARTS = {"dense": _TRACKER_PARTS["dense"], "shape": _TRACKER_PARTS["shape"], "sparse": _TRACKER_PARTS["sparse"],
         "outputs": _outputs, "parallel": _TRACKER_PARTS["parallel"]}


def warm(*parts: str) -> None:
    """Compile the kernels of ``parts`` (default: every part, one after the other)."""
    for name in parts or tuple(PARTS):
        PARTS[name]()


if __name__ == "__main__":
    unknown = [p for p in sys.argv[1:] if p not in PARTS]
    if unknown:
        raise SystemExit(f"error: unknown warm-up part(s) {', '.join(unknown)}; known: {', '.join(PARTS)}")
    warm(*sys.argv[1:])
