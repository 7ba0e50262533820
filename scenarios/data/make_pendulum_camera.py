"""Write pendulum_camera.csv: a camera's view of the pendulum of scenarios/pendulum_fit.toml.

The "true" pendulum (l = 0.75 m, b = 0.03 N·s/m, th0 = 0.35 rad; the scene's [parameters]
hold rougher guesses) is run with constrained (dopri, rtol 1e-10) and sampled at 30 frames
per second for 5 s; each coordinate gets Gaussian noise of 1 mm (NumPy's generator, seed
2024), as a camera tracking the bob would report it. Run it from anywhere:

    python scenarios/data/make_pendulum_camera.py            # rewrites the CSV beside it
    python scenarios/data/make_pendulum_camera.py OUT.csv --seed 7 --noise 0.002
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import constrained as C

HERE = Path(__file__).resolve().parent
SCENE = HERE.parent / "pendulum_fit.toml"
TRUE = {"l": 0.75, "b": 0.03, "th0": 0.35}
FPS, DURATION, NOISE, SEED = 30, 5.0, 0.001, 2024


def camera(seed: int = SEED, noise: float = NOISE, true: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(t (T,), positions (T, 2)): the bob's x, y at the camera's frames, with noise."""
    scene = C.load_scene(SCENE)
    t = np.arange(int(round(DURATION * FPS)) + 1) / FPS
    run = C.simulate(scene.system, t[-1], t_eval=t, method="dopri", rtol=1e-10, atol=1e-12,
                     parameters=dict(TRUE if true is None else true))
    rng = np.random.default_rng(seed)
    return t, run.x[:, 0, :2] + noise * rng.standard_normal((len(t), 2))


def write(path: Path, t: np.ndarray, xy: np.ndarray) -> None:
    lines = ["t,x_bob,y_bob"] + [f"{ti:.6f},{x:.6f},{y:.6f}" for ti, (x, y) in zip(t, xy, strict=True)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default=str(HERE / "pendulum_camera.csv"))
    parser.add_argument("--seed", type=int, default=SEED)
    parser.add_argument("--noise", type=float, default=NOISE, help="standard deviation in metres")
    args = parser.parse_args()
    write(Path(args.out), *camera(args.seed, args.noise))
    print(f"wrote {args.out}")
