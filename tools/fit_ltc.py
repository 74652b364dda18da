"""Fit the linearly transformed cosines (LTC) of the GGX lobe that core.ltc reads, and write them
into core/ltc_table.py.

    .venv/bin/python tools/fit_ltc.py [--size 32] [--samples 4096]

For each view angle and roughness of the table, the lobe the shading uses (core.shading.ggx_parts
with F = 1: D G / (4 n.v), its cosine included), normalised to integrate to 1, is approximated by a
clamped cosine seen through a 3x3 matrix (Heitz, Dupuy, Hill, Neubelt 2016, "Real-Time
Polygonal-Light Shading with Linearly Transformed Cosines"): in a frame with the normal on +z and
the view in the xz plane (x >= 0), the inverse matrix [[a, 0, b], [0, c, 0], [d, 0, 1]] takes a
direction into the cosine's space. Its four numbers minimise the mean cubed difference of the two
densities over directions drawn half from each (their mixture's density weighs them), by
Nelder-Mead, each cell started from its fitted neighbour (rough to smooth, normal to grazing).
The table's error against the lobe integrated over polygons is tested in tests/test_ltc.py.
"""

import argparse
import base64
import math
from pathlib import Path

import numpy as np

from splatwright.core.shading import ALPHA_MIN, ggx_d, ggx_parts

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "core" / "ltc_table.py"
# Above this roughness the fitted cosines leave a glossy highlight further off than core.lights'
# samples do (grazing views: the GGX lobe's tail towards the normal is no transformed cosine), so
# core.ltc integrates smoother lobes only and the table spans [0, ROUGHNESS].
ROUGHNESS = 0.25


def lobe(view, directions, alpha):
    """(S,) the GGX lobe with F = 1 towards `directions` (S,3), normal +z, for one view (3,)."""
    s = len(directions)
    normal = np.broadcast_to([0.0, 0.0, 1.0], (s, 3))
    scalar, _ = ggx_parts(normal, np.broadcast_to(view, (s, 3)), directions, np.full(s, alpha))
    return scalar


def lobe_samples(view, alpha, u1, u2):
    """Directions (S,3) reflected about half-vectors drawn from D, and their density (S,)."""
    cos_h = np.sqrt((1.0 - u1) / (1.0 + (alpha * alpha - 1.0) * u1))
    sin_h = np.sqrt(np.maximum(1.0 - cos_h * cos_h, 0.0))
    phi = 2.0 * math.pi * u2
    half = np.stack([sin_h * np.cos(phi), sin_h * np.sin(phi), cos_h], axis=1)
    vh = half @ view
    return 2.0 * vh[:, None] * half - view, _half_density(cos_h, vh, alpha)


def lobe_density(view, alpha, directions):
    """(S,) the density of lobe_samples at `directions` (S,3)."""
    half = directions + view
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-300)
    return _half_density(np.clip(half[:, 2], 0.0, 1.0), half @ view, alpha)


def _half_density(cos_h, vh, alpha):
    """A reflected direction's density from its half-vector's, D (n.h), over |dl / dh| = 4 |v.h|."""
    return ggx_d(cos_h, np.full(len(cos_h), alpha)) * cos_h / (4.0 * np.maximum(np.abs(vh), 1e-12))


def inverse_matrix(params):
    a, b, c, d = params
    return np.array([[a, 0.0, b], [0.0, c, 0.0], [d, 0.0, 1.0]])


def ltc_density(inverse, directions):
    """(S,) the LTC density of `inverse` (3,3) at unit `directions` (S,3)."""
    o = directions @ inverse.T
    length = np.linalg.norm(o, axis=1)
    cos_o = o[:, 2] / np.maximum(length, 1e-300)
    return np.maximum(cos_o, 0.0) / math.pi * abs(np.linalg.det(inverse)) / np.maximum(length, 1e-300) ** 3


def ltc_samples(inverse, u1, u2):
    """Directions (S,3) drawn from the LTC of `inverse`: a cosine's, through the matrix."""
    r, phi = np.sqrt(u1), 2.0 * math.pi * u2
    cosine = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u1, 0.0))], axis=1)
    out = cosine @ np.linalg.inv(inverse).T
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def fit_error(params, view, alpha, norm, lobe_dirs, u):
    """The mean cubed density difference over the lobe's samples `lobe_dirs` and the LTC's own."""
    inverse = inverse_matrix(params)
    if not np.all(np.isfinite(inverse)) or np.linalg.det(inverse) <= 1e-12 or params[0] <= 0 or params[2] <= 0:
        return 1e30
    dirs = np.concatenate([lobe_dirs, ltc_samples(inverse, *u)])
    target = lobe(view, dirs, alpha) / norm
    density = ltc_density(inverse, dirs)
    mix = 0.5 * lobe_density(view, alpha, dirs) + 0.5 * density
    return float(np.mean(np.abs(density - target) ** 3 / np.maximum(mix, 1e-30)))


def nelder_mead(f, x0, step, iterations=400, tolerance=1e-9):
    """Minimise f from x0 (the simplex spans x0 + step e_i)."""
    simplex = [np.array(x0, float)] + [np.array(x0, float) + step * e for e in np.eye(len(x0))]
    values = [f(x) for x in simplex]
    for _ in range(iterations):  # a loop over the optimiser's steps
        order = np.argsort(values)
        simplex, values = [simplex[i] for i in order], [values[i] for i in order]
        if abs(values[-1] - values[0]) <= tolerance * (abs(values[0]) + 1e-30):
            break
        centre = np.mean(simplex[:-1], axis=0)
        reflected = centre + (centre - simplex[-1])
        fr = f(reflected)
        if fr < values[0]:
            expanded = centre + 2.0 * (centre - simplex[-1])
            fe = f(expanded)
            simplex[-1], values[-1] = (expanded, fe) if fe < fr else (reflected, fr)
        elif fr < values[-2]:
            simplex[-1], values[-1] = reflected, fr
        else:
            contracted = centre + 0.5 * (simplex[-1] - centre)
            fc = f(contracted)
            if fc < values[-1]:
                simplex[-1], values[-1] = contracted, fc
            else:  # shrink towards the best
                simplex = [simplex[0]] + [simplex[0] + 0.5 * (x - simplex[0]) for x in simplex[1:]]
                values = [values[0]] + [f(x) for x in simplex[1:]]
    best = int(np.argmin(values))
    return simplex[best], values[best]


def fit(size, samples, roughness):
    """(size, size, 4) float64: [i, j] the inverse matrix's (a, b, c, d) at view node i (sqrt(1 - n.v)
    = i / (size - 1)) and roughness node j (roughness j / (size - 1), alpha its square, at least
    ALPHA_MIN)."""
    rng = np.random.default_rng(0)
    side = int(math.sqrt(samples))
    grid = (np.arange(side) + 0.5) / side
    u1, u2 = (m.ravel() for m in np.meshgrid(grid, grid, indexing="ij"))
    jitter = rng.uniform(-0.5, 0.5, (2, side * side)) / side
    u = (np.clip(u1 + jitter[0], 0, 1 - 1e-9), np.clip(u2 + jitter[1], 0, 1 - 1e-9))
    table = np.zeros((size, size, 4))
    start = np.array([1.0, 0.0, 1.0, 0.0])
    for j in range(size - 1, -1, -1):  # roughness, rough to smooth
        alpha = max((roughness * j / (size - 1)) ** 2, ALPHA_MIN)
        guess = start
        for i in range(size):  # view, normal to grazing
            t = i / (size - 1)
            cos_v = max(1.0 - t * t, 1e-3)
            view = np.array([math.sqrt(1.0 - cos_v * cos_v), 0.0, cos_v])
            lobe_dirs, lobe_pdf = lobe_samples(view, alpha, *u)
            values = lobe(view, lobe_dirs, alpha)
            norm = float(np.mean(values / np.maximum(lobe_pdf, 1e-300)))  # the lobe's integral
            scale = max(abs(guess[0]), abs(guess[2]))
            best, error = nelder_mead(lambda p: fit_error(p, view, alpha, norm, lobe_dirs, u), guess, 0.05 * scale)
            table[i, j] = best
            guess = best
            if i == 0:
                start = best
        print(f"roughness {roughness * j / (size - 1):.3f}: error {error:.3g}", flush=True)
    return table


def write(table, roughness):
    data = base64.b64encode(table.astype("<f4").tobytes()).decode()
    lines = [data[k : k + 100] for k in range(0, len(data), 100)]
    body = "\n".join(f'    "{line}"' for line in lines)
    OUT.write_text(
        '"""The GGX lobe\'s linearly transformed cosines, as tools/fit_ltc.py fitted them (do not edit: run it).\n\n'
        "INVERSE[i, j] holds (a, b, c, d) of the inverse matrix [[a, 0, b], [0, c, 0], [d, 0, 1]] at view node i\n"
        "(sqrt(1 - n.v) = i / (SIZE - 1)) and roughness node j (ROUGHNESS j / (SIZE - 1)); core.ltc reads them.\n"
        '"""\n\nimport base64\n\nimport numpy as np\n\n'
        f"SIZE = {table.shape[0]}\n"
        f"ROUGHNESS = {roughness!r}  # the roughest lobe fitted\n"
        f"_DATA = (\n{body}\n)\n"
        'INVERSE = np.frombuffer(base64.b64decode(_DATA), "<f4").reshape(SIZE, SIZE, 4).astype(np.float64)\n'
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--samples", type=int, default=4096)
    parser.add_argument("--roughness", type=float, default=ROUGHNESS, help="the roughest lobe fitted")
    args = parser.parse_args()
    write(fit(args.size, args.samples, args.roughness), args.roughness)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
