"""How long writing an animation takes: 120 frames of a planar and of a 3-D scene (issue 32).

    PYTHONPATH=. python benchmarks/gif_writing.py [--repeats 3]

Each scene is run once (dense output, so the animation gets its 120 frames), then
``save_animation`` writes ``animation.gif`` ``--repeats`` times (with ffmpeg on PATH, the MP4
from the same frames too); the best time is printed with where it goes (drawing by blitting,
mapping to the palette, Pillow's GIF encoder). The goal: at most 5 s for 120 frames.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

import constrained as C  # noqa: E402
from constrained.output.animation import save_animation  # noqa: E402

SCENES = (("double_pendulum.toml", "simulate.t_end=10"), ("spherical_pendulum.toml", "simulate.t_end=5"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--profile", action="store_true", help="print the 12 most costly functions")
    args = parser.parse_args()
    for name, end in SCENES:
        scene = C.load_scene(ROOT / "scenarios" / name, [end, "simulate.output_dt=0.01", "expect={}"])
        traj = scene.run().trajectory
        best = float("inf")
        with tempfile.TemporaryDirectory() as out:
            for _ in range(args.repeats):
                started = time.perf_counter()
                written = save_animation(traj, Path(out) / "animation.gif", system=scene.system)
                best = min(best, time.perf_counter() - started)
            size = written[0].stat().st_size
            if args.profile:
                profile = cProfile.Profile()
                profile.runcall(save_animation, traj, Path(out) / "animation.gif", system=scene.system)
                pstats.Stats(profile).sort_stats("tottime").print_stats(12)
        print(f"{name}: {best:.2f} s for the animation ({', '.join(p.suffix for p in written)}, "
              f"GIF {size / 1e6:.1f} MB), best of {args.repeats}")


if __name__ == "__main__":
    main()
