"""Float64 brute-force reference renderer, for tests and benchmarks only.

Every splat is evaluated at every pixel (or at a given subset of pixels) with the conventions of
the 3DGS reference rasteriser written out literally: full 3x3 / 2x3 matrix products for the EWA
covariance, an explicit 2x2 inverse, and a sequential front-to-back loop over splats that applies
the 1/255 skip, the 0.99 clamp and the T < 1e-4 stop pixel by pixel. It shares no code with
core/render.py; from the core it uses only the quaternion -> matrix helper, which has tests of its
own. SH colours are evaluated here with the basis written out from the literal constants (3DGS's
for degrees 0..3, the Condon-Shortley real harmonics that continue them for degree 4), not core.sh's.
"""

import numpy as np

from splatwright.core import geometry

ALPHA_MIN, ALPHA_MAX, T_MIN, LOW_PASS = 1.0 / 255.0, 0.99, 1e-4, 0.3

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
SH_C4 = (
    2.5033429417967046,
    -1.7701307697799304,
    0.9461746957575601,
    -0.6690465435572892,
    0.10578554691520431,
    -0.6690465435572892,
    0.47308734787878004,
    -1.7701307697799304,
    0.6258357354491761,
)


def sh_basis(directions):
    """(N, 25) real SH basis, degrees 0..4 in 3DGS order, at the normalised directions, float64."""
    d = np.asarray(directions, np.float64)
    x, y, z = (d / np.linalg.norm(d, axis=1, keepdims=True)).T
    xx, yy, zz = x * x, y * y, z * z
    return np.stack(
        [
            np.full_like(x, SH_C0),
            -SH_C1 * y,
            SH_C1 * z,
            -SH_C1 * x,
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
            SH_C4[0] * x * y * (xx - yy),
            SH_C4[1] * y * z * (3 * xx - yy),
            SH_C4[2] * x * y * (7 * zz - 1),
            SH_C4[3] * y * z * (7 * zz - 3),
            SH_C4[4] * (35 * zz * zz - 30 * zz + 3),
            SH_C4[5] * x * z * (7 * zz - 3),
            SH_C4[6] * (xx - yy) * (7 * zz - 1),
            SH_C4[7] * x * z * (xx - 3 * yy),
            SH_C4[8] * (xx * xx - 6 * xx * yy + yy * yy),
        ],
        axis=1,
    )


def sh_colors(coeffs, directions):
    """max(0, 0.5 + sum_k Y_k(d) sh_k) per splat, float64."""
    k = coeffs.shape[1]
    return np.maximum(0.0, 0.5 + np.einsum("nk,nkc->nc", sh_basis(directions)[:, :k], coeffs.astype(np.float64)))


def reference_render(
    cloud, camera, background=(0.0, 0.0, 0.0), mode="classic", pixels=None, t_min=T_MIN, layer=None, gather=None
):
    """Returns a dict with color (.., 3), alpha, depth and counts, float64 (counts int), and
    max_weight (N,): each splat's largest blending weight T * alpha over the pixels, 0 if none.

    pixels: optional (M, 2) integer array of (column, row) to evaluate; the outputs are then (M, ...)
    instead of (H, W, ...).
    layer: optional (color (.., 3) premultiplied, alpha, depth) of a surface, composited once per
    pixel just before the first splat whose depth is not in front of it (or after the last); the
    result then also holds layer_t, the T it was composited with. A list of such surfaces (each
    behind the one before it wherever both are present) gives layer_t as a list.
    gather: optional (.., C) image; the result then holds gathered (N, C), each splat's sum over
    the pixels of its weight T * alpha times the image.
    """
    if pixels is None:
        rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
        px, py = cols.ravel() + 0.5, rows.ravel() + 0.5
    else:
        pixels = np.asarray(pixels)
        px, py = pixels[:, 0] + 0.5, pixels[:, 1] + 0.5
    splats = _project_all(cloud, camera, mode)

    m = len(px)
    trans = np.ones(m)
    color = np.zeros((m, 3))
    depth_sum = np.zeros(m)
    counts = np.zeros(m, dtype=np.int64)
    done = np.zeros(m, bool)
    max_weight = np.zeros(len(cloud))
    image = None if gather is None else np.asarray(gather, np.float64).reshape(m, -1)
    gathered = None if gather is None else np.zeros((len(cloud), image.shape[1]))
    surfaces = [] if layer is None else [layer] if isinstance(layer, tuple) else list(layer)
    surfaces = [[np.asarray(a, np.float64).reshape(m, -1) for a in s] for s in surfaces]
    waiting, layer_t = [np.ones(m, bool) for _ in surfaces], [np.zeros(m) for _ in surfaces]

    def cross(j, where):
        """Composite surface j at its waiting pixels in `where`."""
        l_color, l_alpha, _ = surfaces[j]
        where = where & waiting[j]
        layer_t[j][where] = trans[where]
        color[where] += trans[where, None] * l_color[where]
        trans[where] *= 1.0 - l_alpha[where, 0]
        waiting[j][where] = False

    chunk = max(1, 4_000_000 // max(m, 1))
    for start in range(0, len(splats["z"]), chunk):
        sl = slice(start, start + chunk)
        dx = px[None, :] - splats["mean"][sl, 0, None]
        dy = py[None, :] - splats["mean"][sl, 1, None]
        con = splats["conic"][sl]
        q = con[:, 0, 0, None] * dx * dx + 2 * con[:, 0, 1, None] * dx * dy + con[:, 1, 1, None] * dy * dy
        alpha = np.minimum(ALPHA_MAX, splats["opacity"][sl, None] * np.exp(-0.5 * q))
        for k in np.flatnonzero((alpha >= ALPHA_MIN).any(axis=1)):
            for j, (_, _, l_depth) in enumerate(surfaces):
                cross(j, splats["z"][start + k] >= l_depth[:, 0])
            a = alpha[k]
            use = ~done & (a >= ALPHA_MIN)
            test = trans * (1.0 - a)
            stop = use & (test < t_min)
            done |= stop
            use &= ~stop
            w = np.where(use, trans * a, 0.0)
            color += w[:, None] * splats["color"][start + k]
            depth_sum += w * splats["z"][start + k]
            counts += use
            max_weight[splats["index"][start + k]] = w.max(initial=0.0)
            if image is not None:
                gathered[splats["index"][start + k]] = w @ image
            trans = np.where(use, test, trans)

    for j in range(len(surfaces)):
        cross(j, np.ones(m, bool))
    alpha = 1.0 - trans
    out = {
        "color": color + trans[:, None] * np.asarray(background, dtype=np.float64),
        "alpha": alpha,
        "depth": np.where(alpha > 0, depth_sum / np.where(alpha > 0, alpha, 1.0), 0.0),
        "counts": counts,
    }
    if surfaces:  # depth and alpha of the splats alone, without the surfaces' share
        out["layer_t"] = layer_t[0] if isinstance(layer, tuple) else np.stack(layer_t, axis=-1)
        splat_alpha = alpha - sum(t * s[1][:, 0] for t, s in zip(layer_t, surfaces))
        out["depth"] = np.where(splat_alpha > 0, depth_sum / np.where(splat_alpha > 0, splat_alpha, 1.0), 0.0)
    if pixels is None:
        out = {k: v.reshape((camera.height, camera.width) + v.shape[1:]) for k, v in out.items()}
    out["max_weight"] = max_weight
    if gathered is not None:
        out["gathered"] = gathered
    return out


def _project_all(cloud, camera, mode):
    """Per-splat pixel mean, 2D conic, opacity, colour, depth and cloud index of the splats in
    front of the camera, sorted by depth with ties in index order."""
    fields = (
        cloud.positions,
        cloud.rotations,
        cloud.log_scales,
        cloud.opacity_logits[:, None],
        cloud.sh.reshape(len(cloud), -1),
    )
    finite = np.all([np.isfinite(f).all(axis=1) for f in fields], axis=0)
    idx = np.flatnonzero(finite)
    pos = cloud.positions[idx].astype(np.float64)
    w2c = camera.world_to_camera
    cam = pos @ w2c[:3, :3].T + w2c[:3, 3]
    with np.errstate(over="ignore"):
        opacity = 1.0 / (1.0 + np.exp(-cloud.opacity_logits[idx].astype(np.float64)))
    z = cam[:, 2]
    keep = (z > camera.near) & (z <= camera.far)
    idx, pos, cam, z, opacity = idx[keep], pos[keep], cam[keep], z[keep], opacity[keep]
    order = np.argsort(z.astype(np.float32), kind="stable")  # float32 depth keys, ties by index
    idx, pos, cam, z, opacity = idx[order], pos[order], cam[order], z[order], opacity[order]

    rot = geometry.quaternions_to_matrices(cloud.rotations[idx])
    s2 = np.exp(2.0 * cloud.log_scales[idx].astype(np.float64))
    sigma = np.einsum("nij,nj,nkj->nik", rot, s2, rot)
    n = len(idx)
    jac = np.zeros((n, 2, 3))
    if camera.projection == "orthographic":
        jac[:, 0, 0], jac[:, 1, 1] = camera.fx, camera.fy
        mean = np.stack([camera.fx * cam[:, 0] + camera.cx, camera.fy * cam[:, 1] + camera.cy], axis=1)
        directions = np.tile(w2c[2, :3], (n, 1))
    else:
        w, h = camera.width, camera.height
        lim_x = ((-camera.cx - 0.15 * w) / camera.fx, (w - camera.cx + 0.15 * w) / camera.fx)
        lim_y = ((-camera.cy - 0.15 * h) / camera.fy, (h - camera.cy + 0.15 * h) / camera.fy)
        tx = np.clip(cam[:, 0] / z, *lim_x) * z
        ty = np.clip(cam[:, 1] / z, *lim_y) * z
        jac[:, 0, 0] = camera.fx / z
        jac[:, 0, 2] = -camera.fx * tx / z**2
        jac[:, 1, 1] = camera.fy / z
        jac[:, 1, 2] = -camera.fy * ty / z**2
        mean = np.stack([camera.fx * cam[:, 0] / z + camera.cx, camera.fy * cam[:, 1] / z + camera.cy], axis=1)
        directions = pos - camera.center
    t = jac @ w2c[:3, :3]
    cov = t @ sigma @ np.swapaxes(t, 1, 2)
    det0 = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    cov = cov + LOW_PASS * np.eye(2)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0]
    if mode == "antialiased":
        opacity = opacity * np.sqrt(np.maximum(0.000025, det0 / det))
    conic = (
        np.stack([np.stack([cov[:, 1, 1], -cov[:, 0, 1]], -1), np.stack([-cov[:, 1, 0], cov[:, 0, 0]], -1)], 1)
        / det[:, None, None]
    )
    color = sh_colors(cloud.sh[idx], directions) if n else np.zeros((0, 3))
    return {"mean": mean, "conic": conic, "opacity": opacity, "color": color, "z": z, "index": idx}
