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

WebP is decoded and encoded through io.image's codecs: Pillow's, or where Pillow is missing (Blender's
own Python) Blender's, which the extension registers. Blender's encoder is not exact: it replaces the
colour of fully transparent pixels. Only sh0 has such pixels (every other image's alpha is 252 or
more), one for each splat of opacity byte 0 (opacity under 1/510), which no viewer draws (renderers
skip what stays under alpha 1/255). Such splats are kept, so every other splat reads back exactly as
from Pillow's file (the codebooks, bounds and palette are found over all splats), and a warning counts
those whose base colour (SH band 0) is not kept.

Before a pixel is decoded, every image's size is taken from its WebP header and checked against the
splat count and io.policy.MAX_IMAGE_PIXELS, and the count against the bytes the file stores (see
SOG_MAX_RATIO); a bundle entry may inflate to at most ENTRY_MAX_RATIO times its stored size. Loose
images are read under the reading policy (io/policy.py): regular files in the meta.json's folder.
"""

import json
import os
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
    check_file,
    check_nonfinite_policy,
    publish_together,
    reduced_sh,
    warn_notes,
)
from .compressed_ply import morton_order
from .image import check_image_size, decode_webp, encode_webp, header_size, webp_codec
from .policy import referenced_file

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
# A bundle entry may inflate to at most this many times its stored size once past the floor: WebP
# images do not deflate at all, JSON a few times.
ENTRY_MAX_RATIO = 64
ENTRY_RATIO_FLOOR = 1 << 20
# The numbers a SOG decodes to (3 + 4 + 3 + 1 + 3 per SH coefficient per splat): at most
# SOG_RATIO_FLOOR (1.2M splats without SH, 280K at degree 3; any file under 1 MiB) or SOG_MAX_RATIO
# per byte its meta.json and images store. Real captures store about 14 bytes per splat (1 number per
# byte), a cubic grid of identical splats 13 numbers per byte; a flat grid (24) reads up to the floor.
# A one-colour 5000x5000 WebP is 38 bytes.
SOG_RATIO_FLOOR = 1 << 24
SOG_MAX_RATIO = 16
SQRT2 = np.sqrt(2.0)


def _codec(path, job):
    """Refuse (SplatFileError saying what is missing) where no WebP codec can `job` ("decode", "encode")."""
    if webp_codec(job) is not None:
        return
    if job == "encode" and webp_codec("decode") is not None:
        raise SplatFileError(
            path,
            "SOG stores splats as lossless WebP images and this Python has a WebP decoder but no encoder "
            "(the Pillow package; in Blender, the Splatwright extension lends Blender's)",
        )
    raise SplatFileError(
        path,
        "SOG stores splats as WebP images and this Python has no WebP codec (the Pillow package; "
        "Blender's own Python lacks it): in Blender, the Splatwright extension lends Blender's decoder",
    )


# reading ------------------------------------------------------------------------------------------


class _Source:
    """The files of a SOG: entries of a .sog zip, or files beside a meta.json (the folder of the
    file a symbolic link names, where the writer puts them). `stored` counts the bytes read."""

    def __init__(self, path, allow_outside=False):
        self.path, self.allow_outside = path, allow_outside
        self.zip = None
        self.stored = 0
        if not str(path).lower().endswith("meta.json"):
            try:
                self.zip = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError, EOFError) as exc:
                raise SplatFileError(path, f"not a SOG bundle (a zip of meta.json and WebP images): {exc}") from None

    def meta(self):
        """The bytes of meta.json: the bundle's entry, or the file itself."""
        return self.read("meta.json") if self.zip is not None else self._file(self.path, "meta.json")

    def read(self, name):
        """The bytes of an image (or meta.json) the SOG names."""
        if self.zip is not None:
            return self._entry(name)
        folder = Path(os.path.realpath(self.path)).parent
        return self._file(referenced_file(self.path, name, folder, folder, self.allow_outside, "SOG image"), name)

    def _file(self, target, name):
        try:
            with open(target, "rb") as f:
                data = f.read(MAX_FILE + 1)
        except OSError as exc:
            raise SplatFileError(self.path, f"cannot read {name}: {exc.strerror or exc}") from None
        if len(data) > MAX_FILE:
            raise SplatFileError(self.path, f"{name} holds more than {MAX_FILE} bytes, more than a SOG file may")
        self.stored += len(data)
        return data

    def _entry(self, name):
        try:
            info = self.zip.getinfo(name)
        except KeyError:
            raise SplatFileError(self.path, f"the bundle has no {name}") from None
        inflated = info.file_size > max(ENTRY_RATIO_FLOOR, ENTRY_MAX_RATIO * info.compress_size)
        if info.file_size > MAX_FILE or inflated:
            raise SplatFileError(
                self.path,
                f"{name} claims {info.file_size} bytes from {info.compress_size} stored, more than a SOG entry may "
                f"hold (at most {MAX_FILE}, and {ENTRY_MAX_RATIO} times its stored size)",
            )
        try:
            data = self.zip.read(info)
        except (zipfile.BadZipFile, OSError, EOFError, NotImplementedError) as exc:
            raise SplatFileError(self.path, f"cannot read {name} from the bundle: {exc}") from None
        self.stored += info.compress_size
        return data

    def close(self):
        if self.zip is not None:
            self.zip.close()


class _Image:
    """A SOG image read but not decoded: its bytes, and its size from its header, checked to hold
    between `least` and `most` pixels (and no more than policy.MAX_IMAGE_PIXELS); `what` they are for."""

    def __init__(self, path, source, name, least, most, what):
        self.path, self.name, self.data = path, name, source.read(name)
        size = header_size(self.data)
        if size is None:
            raise SplatFileError(path, f"{name} is not a WebP image (its header states no size)")
        self.size = width, height = size
        check_image_size(path, width, height, name)
        if not least <= width * height <= most:
            raise SplatFileError(path, f"{name} is {width}x{height} pixels for {what}")

    def pixels(self):
        """(H*W, 4) uint8 RGBA."""
        return decode_webp(self.path, self.data, self.name).reshape(-1, 4)


def _splat_image(path, source, name, count):
    """A per-splat image: at least `count` pixels, at most what a writer's padding adds."""
    return _Image(path, source, name, count, 4 * count + (1 << 20), f"{count} splats")


def _meta(path, source):
    try:
        meta = json.loads(source.meta())
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
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
        files = {k: _files(path, meta[k], k, len(FILES[k])) for k in ("means", "scales", "quats", "sh0")}
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise SplatFileError(path, f"meta.json lacks or garbles {exc}") from None
    if count < 0 or mins.shape != (3,) or maxs.shape != (3,) or any(c.shape != (CODEBOOK,) for c in codebooks.values()):
        raise SplatFileError(path, "meta.json: count, means.mins/maxs (3 each) or 256-entry codebooks are malformed")
    return meta, count, mins, maxs, codebooks, files


def _files(path, section, key, number):
    """The `number` image names a section of meta.json lists."""
    names = section.get("files") if isinstance(section, dict) else None
    if not isinstance(names, list) or len(names) != number or not all(isinstance(n, str) and n for n in names):
        raise SplatFileError(path, f"meta.json: {key}.files must list {number} image names, not {names!r:.100}")
    return names


def _sh_meta(path, shn):
    """(SH degree, palette entries, codebook, image names) of meta.json's shN."""
    try:
        bands, count = int(shn["bands"]), int(shn["count"])
        codebook = np.asarray(shn["codebook"], np.float32)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise SplatFileError(path, f"meta.json shN lacks or garbles {exc}") from None
    if bands not in SH_COEFFS or codebook.shape != (CODEBOOK,) or not 0 < count <= PALETTE_MAX:
        raise SplatFileError(path, f"meta.json shN: bands {bands}, count {count} or its codebook is malformed")
    return bands, count, codebook, _files(path, shn, "shN", 2)


def decode(path, source):
    """The cloud a SOG holds; every image's size and the count checked before any is decoded."""
    meta, n, mins, maxs, codebooks, files = _meta(path, source)
    images = {key: [_splat_image(path, source, name, n) for name in names] for key, names in files.items()}
    sh_meta = _sh_meta(path, meta["shN"]) if meta.get("shN") else None
    if sh_meta:
        images["shN"] = _sh_images(path, source, sh_meta, n)
    numbers = n * (3 + 4 + 3 + 1 + 3 * (1 + (SH_COEFFS[sh_meta[0]] if sh_meta else 0)))
    limit = max(SOG_RATIO_FLOOR, SOG_MAX_RATIO * source.stored)
    if numbers > limit:
        raise SplatFileError(
            path,
            f"meta.json claims {n} splats, {numbers} numbers to decode: more than the {limit} a SOG storing "
            f"{source.stored} bytes may decode to (a decompression bomb?)",
        )
    lo, hi = (image.pixels()[:n] for image in images["means"])
    quantised = lo[:, :3].astype(np.float64) + 256.0 * hi[:, :3]
    ranges = np.where(maxs - mins == 0, 1.0, maxs - mins)
    logs = mins + ranges * quantised / 65535
    positions = np.sign(logs) * np.expm1(np.abs(logs))
    rotations = _unpack_quats(path, images["quats"][0].pixels()[:n])
    scales = codebooks["scales"][images["scales"][0].pixels()[:n, :3]]
    sh0 = images["sh0"][0].pixels()[:n]
    dc = codebooks["sh0"][sh0[:, :3]]
    logits = logit(sh0[:, 3] / 255.0)
    sh = dc[:, None, :]
    if sh_meta:
        sh = np.concatenate([sh, _sh_rest(sh_meta, *images["shN"], n)], axis=1)
    return SplatCloud(positions, rotations, scales, logits, sh)


def _unpack_quats(path, rgba):
    tag = rgba[:, 3].astype(np.int64) - 252
    bad = (tag < 0) | (tag > 3)
    tag = np.where(bad, 0, tag)
    abc = (rgba[:, :3] / 255.0 * 2 - 1) / SQRT2
    largest = np.sqrt(np.maximum(0, 1 - (abc * abc).sum(axis=1)))
    q = np.empty((len(rgba), 4))
    for j in range(4):  # component j is abc[j] before the largest, abc[j - 1] after it (column-wise: fast)
        q[:, j] = np.where(tag == j, largest, np.where(j < tag, abc[:, min(j, 2)], abc[:, max(j - 1, 0)]))
    q[bad] = (1, 0, 0, 0)  # as the reference decoder does
    return q


def _sh_images(path, source, sh_meta, n):
    """[centroids image, labels image] of meta.json's shN."""
    bands, count, _, names = sh_meta
    texels = -(-count // 64) * 64 * SH_COEFFS[bands]  # rows of 64 entries, k texels each
    centroids = _Image(path, source, names[0], texels, texels + (1 << 20), f"{count} palette entries")
    return [centroids, _splat_image(path, source, names[1], n)]


def _sh_rest(sh_meta, centroids, labels, n):
    """(n, k, 3) SH above degree 0 from the palette and each splat's label."""
    bands, count, codebook, _ = sh_meta
    k = SH_COEFFS[bands]
    rows = -(-count // 64)
    palette = codebook[centroids.pixels()[: rows * 64 * k, :3]].reshape(rows * 64, k, 3)
    labels = labels.pixels()[:n]
    index = labels[:, 0].astype(np.int64) | (labels[:, 1].astype(np.int64) << 8)
    out = np.zeros((n, k, 3), np.float32)
    ok = index < count
    out[ok] = palette[index[ok]]
    return out


def read(path, nonfinite="raise", allow_outside=False):
    """Read a .sog bundle or a SOG meta.json (with its images beside it) into a SplatCloud.
    allow_outside: also read loose images outside the meta.json's folder (special files never)."""
    check_nonfinite_policy(nonfinite)
    check_file(path)
    _codec(path, "decode")
    source = _Source(path, allow_outside)
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


def _bytes(x):
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _opacity_bytes(cloud):
    """sh0's alpha: each splat's opacity * 255."""
    return _bytes(sigmoid(cloud.opacity_logits) * 255)


def _invisible_note(cloud, notes):
    """Where the WebP encoder replaces the colour of fully transparent pixels, a note counting the
    splats of opacity byte 0 (drawn by no viewer), whose sh0 pixel is such a pixel."""
    codec = webp_codec("encode")
    invisible = int(np.count_nonzero(_opacity_bytes(cloud) == 0))
    if codec is not None and not codec.exact and invisible:
        notes.append(
            f"{invisible} splats of opacity under 1/510 (drawn by no viewer) kept without their base colour (SH "
            f"band 0): {codec.name}'s WebP encoder replaces the colour of fully transparent pixels"
        )


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
    alpha = _opacity_bytes(cloud)
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
    out = {name: encode_webp(path, pixels) for name, pixels in files.items()}
    out["meta.json"] = json.dumps(meta).encode("utf-8")
    return out


def write(path, cloud, order="morton", nonfinite="raise"):
    """Write a .sog bundle, or (a path ending in meta.json) meta.json and its WebP images beside it
    (through a symbolic link: beside the file it names).
    order="morton" sorts the splats along a Morton curve as PlayCanvas does; None keeps the order."""
    _codec(path, "encode")
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
    _invisible_note(cloud, notes)
    warn_notes(path, notes)
    files = encode(path, cloud)
    if str(path).lower().endswith("meta.json"):
        folder = Path(os.path.realpath(path)).parent  # beside the file a symbolic link names
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
