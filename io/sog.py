"""PlayCanvas SOG (version 2): splats as lossless WebP images plus a meta.json, bundled in a zip
(`.sog`) or as loose files beside a `meta.json`.

Every image holds one splat per pixel, row by row (width a multiple of 4 near sqrt(N), height
padded to a multiple of 4):
    means_l, means_u  low and high bytes of 16-bit positions per axis (RGB), after the log
                      transform sign(x) ln(|x| + 1), spread over meta.means.mins..maxs
    quats             the three smaller components of the unit quaternion (w, x, y, z order), the
                      largest made positive, each as q * sqrt(2) mapped to 0..255; alpha = 252 + the
                      largest's index
    scales            log scales (RGB) as indices into meta.scales.codebook (256 floats)
    sh0               f_dc (RGB) as indices into meta.sh0.codebook; alpha = opacity * 255
    shN_labels        (degree > 0) a 16-bit palette index (R low, G high) per splat
    shN_centroids     the palette: 64 entries per row, each entry (2l+1)... coefficients wide, RGB
                      channels as indices into meta.shN.codebook
The writer orders splats along a Morton curve (as PlayCanvas does), finds the 256-entry codebooks by
1-D k-means, and gives every splat its own palette entry up to 65,536 splats (beyond that, entries
are the means of a balanced k-d split of the SH vectors). Extras are not stored.

WebP is decoded and encoded by Pillow. Blender's own Python has no Pillow: there SOG files cannot be
read or written, and the error says so (convert them with the `splatwright` command outside).
"""

import io
import json
import warnings
import zipfile
from pathlib import Path

import numpy as np

from ..core import SplatCloud
from ..core.splats import logit, sigmoid
from .common import (
    SplatFileError,
    SplatFileWarning,
    apply_nonfinite_policy,
    atomic_write,
    check_nonfinite_policy,
    publish_together,
    reduced_sh,
    warn_notes,
)
from .compressed_ply import morton_order

FILES = {
    "means": ["means_l.webp", "means_u.webp"],
    "scales": ["scales.webp"],
    "quats": ["quats.webp"],
    "sh0": ["sh0.webp"],
    "shN": ["shN_centroids.webp", "shN_labels.webp"],
}
SH_COEFFS = {1: 3, 2: 8, 3: 15}
PALETTE_MAX = 1 << 16
CODEBOOK = 256
MAX_FILE = 1 << 30  # an entry of a .sog bigger than this is refused before reading
SQRT2 = np.sqrt(2.0)


def _pillow(path):
    """Pillow's Image module with its WebP codec, or a SplatFileError saying what is missing."""
    try:
        from PIL import Image, features
    except ImportError:
        raise SplatFileError(
            path,
            "SOG stores splats as WebP images and this Python has no WebP codec (the "
            "Pillow package; Blender's own Python lacks it): convert the file with "
            "the splatwright command outside Blender",
        ) from None
    if not features.check("webp"):
        raise SplatFileError(path, "SOG stores splats as WebP images and this Pillow was built without WebP")
    return Image


# reading ------------------------------------------------------------------------------------------


class _Source:
    """The files of a SOG: entries of a .sog zip, or files beside a meta.json."""

    def __init__(self, path):
        self.path = path
        self.zip = None
        if not str(path).lower().endswith("meta.json"):
            try:
                self.zip = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError, EOFError) as exc:
                raise SplatFileError(path, f"not a SOG bundle (a zip of meta.json and WebP images): {exc}") from None

    def read(self, name):
        if self.zip is None:
            target = Path(self.path).parent / name
            if Path(name).name != name:
                raise SplatFileError(self.path, f"meta.json names the file '{name}' outside its folder")
            try:
                return target.read_bytes()
            except OSError as exc:
                raise SplatFileError(self.path, f"cannot read {name}: {exc.strerror or exc}") from None
        try:
            info = self.zip.getinfo(name)
        except KeyError:
            raise SplatFileError(self.path, f"the bundle has no {name}") from None
        if info.file_size > MAX_FILE:
            raise SplatFileError(self.path, f"{name} claims {info.file_size} bytes, more than a SOG entry may hold")
        try:
            return self.zip.read(info)
        except (zipfile.BadZipFile, OSError, EOFError, NotImplementedError) as exc:
            raise SplatFileError(self.path, f"cannot read {name} from the bundle: {exc}") from None

    def close(self):
        if self.zip is not None:
            self.zip.close()


def _image(path, source, name, count):
    """(H*W, 4) uint8 RGBA pixels of a WebP image holding at least `count` pixels."""
    image_module = _pillow(path)
    data = source.read(name)
    try:
        with image_module.open(io.BytesIO(data)) as image:
            if image.format != "WEBP":
                raise SplatFileError(path, f"{name} is {image.format}, not WebP")
            width, height = image.size
            if width * height < count or width * height > 4 * count + (1 << 20):
                raise SplatFileError(path, f"{name} is {width}x{height} pixels for {count} splats")
            pixels = np.asarray(image.convert("RGBA"))
    except SplatFileError:
        raise
    except Exception as exc:  # noqa: BLE001 - Pillow raises many types for damaged images
        raise SplatFileError(path, f"{name} is not a readable WebP image: {exc}") from None
    return pixels.reshape(-1, 4)


def _meta(path, source):
    try:
        meta = json.loads(source.read("meta.json") if source.zip is not None else Path(path).read_bytes())
    except OSError as exc:
        raise SplatFileError(path, f"cannot read: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise SplatFileError(path, f"meta.json is not valid JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise SplatFileError(path, "meta.json must hold an object")
    if meta.get("version") != 2:
        raise SplatFileError(
            path, f"SOG version {meta.get('version', '1 (no version field)')}; this reader takes version 2"
        )
    try:
        count = int(meta["count"])
        mins, maxs = (np.asarray(meta["means"][k], np.float64) for k in ("mins", "maxs"))
        codebooks = {k: np.asarray(meta[k]["codebook"], np.float32) for k in ("scales", "sh0")}
        files = {k: list(meta[k]["files"]) for k in ("means", "scales", "quats", "sh0")}
    except (KeyError, TypeError, ValueError) as exc:
        raise SplatFileError(path, f"meta.json lacks or garbles {exc}") from None
    if count < 0 or mins.shape != (3,) or maxs.shape != (3,) or any(c.shape != (CODEBOOK,) for c in codebooks.values()):
        raise SplatFileError(path, "meta.json: count, means.mins/maxs (3 each) or 256-entry codebooks are malformed")
    return meta, count, mins, maxs, codebooks, files


def decode(path, source):
    meta, n, mins, maxs, codebooks, files = _meta(path, source)
    lo, hi = (_image(path, source, name, n)[:n] for name in files["means"][:2])
    quantised = lo[:, :3].astype(np.float64) + 256.0 * hi[:, :3]
    ranges = np.where(maxs - mins == 0, 1.0, maxs - mins)
    logs = mins + ranges * quantised / 65535
    positions = np.sign(logs) * np.expm1(np.abs(logs))
    rotations = _unpack_quats(path, _image(path, source, files["quats"][0], n)[:n])
    scales = codebooks["scales"][_image(path, source, files["scales"][0], n)[:n, :3]]
    sh0 = _image(path, source, files["sh0"][0], n)[:n]
    dc = codebooks["sh0"][sh0[:, :3]]
    logits = logit(sh0[:, 3] / 255.0)
    sh = dc[:, None, :]
    if meta.get("shN"):
        sh = np.concatenate([sh, _sh_rest(path, source, meta["shN"], n)], axis=1)
    return SplatCloud(positions, rotations, scales, logits, sh)


def _unpack_quats(path, rgba):
    tag = rgba[:, 3].astype(np.int64) - 252
    bad = (tag < 0) | (tag > 3)
    tag = np.where(bad, 0, tag)
    abc = (rgba[:, :3] / 255.0 * 2 - 1) / SQRT2
    q = np.zeros((len(rgba), 4))
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[tag]
    rows = np.arange(len(rgba))
    for i in range(3):
        q[rows, others[:, i]] = abc[:, i]
    q[rows, tag] = np.sqrt(np.maximum(0, 1 - (abc * abc).sum(axis=1)))
    q[bad] = (1, 0, 0, 0)  # as the reference decoder does
    return q


def _sh_rest(path, source, shn, n):
    try:
        bands, count = int(shn["bands"]), int(shn["count"])
        codebook = np.asarray(shn["codebook"], np.float32)
        names = list(shn["files"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SplatFileError(path, f"meta.json shN lacks or garbles {exc}") from None
    if bands not in SH_COEFFS or codebook.shape != (CODEBOOK,) or not 0 < count <= PALETTE_MAX:
        raise SplatFileError(path, f"meta.json shN: bands {bands}, count {count} or its codebook is malformed")
    k = SH_COEFFS[bands]
    centroids = _image(path, source, names[0], 0)
    rows = -(-count // 64)
    if len(centroids) < rows * 64 * k:
        raise SplatFileError(
            path, f"{names[0]} holds {len(centroids)} texels, {count} palette entries need {rows * 64 * k}"
        )
    palette = codebook[centroids[: rows * 64 * k, :3]].reshape(rows * 64, k, 3)
    labels = _image(path, source, names[1], n)[:n]
    index = labels[:, 0].astype(np.int64) | (labels[:, 1].astype(np.int64) << 8)
    out = np.zeros((n, k, 3), np.float32)
    ok = index < count
    out[ok] = palette[index[ok]]
    return out


def read(path, nonfinite="raise"):
    """Read a .sog bundle or a SOG meta.json (with its images beside it) into a SplatCloud."""
    check_nonfinite_policy(nonfinite)
    if not Path(path).is_file():
        raise SplatFileError(path, "no such file")
    _pillow(path)
    source = _Source(path)
    try:
        with np.errstate(invalid="ignore", over="ignore"):
            cloud = decode(path, source)
    finally:
        source.close()
    return apply_nonfinite_policy(path, cloud, nonfinite, "read")


# writing ------------------------------------------------------------------------------------------


def kmeans_1d(values, k=CODEBOOK, iterations=12):
    """(centroids (k,) float32 ascending, labels) of 1-D k-means, started at quantiles. On sorted
    values each cluster is a run, so an iteration is k binary searches and prefix-sum differences."""
    v = np.sort(np.asarray(values, np.float64).reshape(-1))
    centroids = np.unique(np.quantile(v, (np.arange(k) + 0.5) / k)) if len(v) else np.zeros(1)
    prefix = np.concatenate([[0.0], np.cumsum(v)])
    for _ in range(iterations):
        edges = np.concatenate([[0], np.searchsorted(v, (centroids[1:] + centroids[:-1]) / 2), [len(v)]])
        counts = np.diff(edges)
        moved = np.where(counts > 0, (prefix[edges[1:]] - prefix[edges[:-1]]) / np.maximum(counts, 1), centroids)
        if np.array_equal(moved, centroids):
            break
        centroids = np.sort(moved)
    centroids = np.pad(centroids, (0, k - len(centroids)), mode="edge").astype(np.float32)
    return centroids, _nearest_1d(np.asarray(values, np.float64).reshape(-1), centroids.astype(np.float64))


def _nearest_1d(v, centroids):
    """Index of the nearest of the ascending centroids for every value."""
    cuts = (centroids[1:] + centroids[:-1]) / 2
    return np.searchsorted(cuts, v).astype(np.int64)


def palette(vectors, size):
    """(centroids, labels): each vector its own entry when they fit in `size`, else the means of a
    balanced k-d split (each group halved at the median of its widest coordinate) into `size` groups."""
    n = len(vectors)
    if n <= size:
        return vectors.astype(np.float32), np.arange(n)
    order = np.arange(n)
    bounds = np.array([0, n])
    while len(bounds) - 1 < size:
        starts, stops = bounds[:-1], bounds[1:]
        grouped = vectors[order]
        lo = np.minimum.reduceat(grouped, starts, axis=0)
        hi = np.maximum.reduceat(grouped, starts, axis=0)
        widest = np.argmax(hi - lo, axis=1)
        group = np.repeat(np.arange(len(starts)), stops - starts)
        key = grouped[np.arange(n), widest[group]]
        order = order[np.lexsort((key, group))]
        bounds = np.unique(np.concatenate([bounds, (starts + stops) // 2]))
    labels = np.empty(n, np.int64)
    labels[order] = np.repeat(np.arange(len(bounds) - 1), np.diff(bounds))
    sums = np.add.reduceat(vectors[order].astype(np.float64), bounds[:-1], axis=0)
    return (sums / np.diff(bounds)[:, None]).astype(np.float32), labels


def _round_up(value, step):
    """The smallest multiple of `step` at or above `value`."""
    return -(-value // step) * step


def _grid(n):
    width = max(4, _round_up(int(np.ceil(np.sqrt(n))), 4))
    height = max(4, _round_up(_round_up(n, width) // width, 4))
    return width, height


def _rgba(values, width, height, alpha=255):
    """A (height, width, 4) uint8 image with one splat's bytes (N, 3 or 4) per pixel."""
    out = np.zeros((width * height, 4), np.uint8)
    out[:, 3] = alpha
    out[: len(values), : values.shape[1]] = values
    return out.reshape(height, width, 4)


def _webp(path, pixels):
    buffer = io.BytesIO()
    _pillow(path).fromarray(pixels, "RGBA").save(buffer, "WEBP", lossless=True, exact=True, quality=50, method=2)
    return buffer.getvalue()


def _bytes(x):
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def encode(path, cloud):
    """{file name: bytes} of a SOG (meta.json included) for a cloud, in its order."""
    n, degree = len(cloud), cloud.sh_degree
    width, height = _grid(n)
    positions = cloud.positions.astype(np.float64)
    logs = np.sign(positions) * np.log1p(np.abs(positions))
    mins, maxs = logs.min(axis=0), logs.max(axis=0)
    span = np.where(maxs > mins, maxs - mins, 1.0)
    q16 = np.clip(np.rint((logs - mins) / span * 65535), 0, 65535).astype(np.uint16)
    files = {
        "means_l.webp": _rgba((q16 & 0xFF).astype(np.uint8), width, height),
        "means_u.webp": _rgba((q16 >> 8).astype(np.uint8), width, height),
    }
    q = cloud.unit_rotations.astype(np.float64)
    largest = np.argmax(np.abs(q), axis=1)
    rows = np.arange(n)
    q *= np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None] * SQRT2
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    abc = np.stack([q[rows, others[:, i]] for i in range(3)], axis=1)
    files["quats.webp"] = _rgba(np.column_stack([_bytes(255 * (abc * 0.5 + 0.5)), 252 + largest]), width, height)
    scale_book, scale_labels = kmeans_1d(cloud.log_scales)
    files["scales.webp"] = _rgba(scale_labels.reshape(n, 3).astype(np.uint8), width, height)
    dc_book, dc_labels = kmeans_1d(cloud.sh[:, 0])
    alpha = _bytes(sigmoid(cloud.opacity_logits) * 255)
    files["sh0.webp"] = _rgba(np.column_stack([dc_labels.reshape(n, 3).astype(np.uint8), alpha]), width, height)
    meta = {
        "version": 2,
        "asset": {"generator": "Splatwright"},
        "count": n,
        "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": FILES["means"]},
        "scales": {"codebook": scale_book.tolist(), "files": FILES["scales"]},
        "quats": {"files": FILES["quats"]},
        "sh0": {"codebook": dc_book.tolist(), "files": FILES["sh0"]},
    }
    if degree:
        k = SH_COEFFS[degree]
        centroids, labels = palette(cloud.sh[:, 1:].reshape(n, -1), PALETTE_MAX)
        book, coded = kmeans_1d(centroids)
        coded = coded.reshape(len(centroids), k, 3).astype(np.uint8)
        rows_of_64 = -(-len(centroids) // 64)
        texels = np.zeros((rows_of_64 * 64, k, 4), np.uint8)
        texels[:, :, 3] = 255
        texels[: len(centroids), :, :3] = coded
        files["shN_centroids.webp"] = texels.reshape(rows_of_64, 64 * k, 4)
        files["shN_labels.webp"] = _rgba(np.column_stack([labels & 0xFF, labels >> 8]).astype(np.uint8), width, height)
        meta["shN"] = {"count": len(centroids), "bands": degree, "codebook": book.tolist(), "files": FILES["shN"]}
    out = {name: _webp(path, pixels) for name, pixels in files.items()}
    out["meta.json"] = json.dumps(meta).encode("utf-8")
    return out


def write(path, cloud, order="morton", nonfinite="raise"):
    """Write a .sog bundle, or (a path ending in meta.json) meta.json and its WebP images beside it.
    order="morton" sorts the splats along a Morton curve as PlayCanvas does; None keeps the order."""
    _pillow(path)
    cloud = apply_nonfinite_policy(path, cloud, nonfinite, "write")
    if not len(cloud):
        raise SplatFileError(path, "SOG cannot hold an empty cloud (its images need at least one splat)")
    if order == "morton":
        cloud = cloud[morton_order(cloud.positions)]
    elif order is not None:
        raise ValueError(f"order must be 'morton' or None, got {order!r}")
    if cloud.extras:
        warnings.warn(
            f"{path}: SOG has no room for extras; {sorted(cloud.extras)} not written", SplatFileWarning, stacklevel=2
        )
    notes = []
    cloud = reduced_sh(cloud, max(SH_COEFFS), "SOG", notes)
    warn_notes(path, notes)
    files = encode(path, cloud)
    if str(path).lower().endswith("meta.json"):
        folder = Path(path).parent
        with publish_together():  # meta.json and its images, or none of them
            for name, data in files.items():
                if name != "meta.json":
                    with atomic_write(folder / name) as f:
                        f.write(data)
            with atomic_write(path) as f:  # renamed last: the images it names are in place
                f.write(files["meta.json"])
        return
    with atomic_write(path) as f, zipfile.ZipFile(f, "w", zipfile.ZIP_STORED) as bundle:
        for name in ["meta.json"] + [name for name in files if name != "meta.json"]:
            bundle.writestr(zipfile.ZipInfo(name, (1980, 1, 1, 0, 0, 0)), files[name])
