"""mkkellogg's GaussianSplats3D `.ksplat` (its SplatBuffer, version 0.1 and later 0.x), read only.

A 4096-byte header, then `max sections` headers of 1024 bytes, then each section's data:
    header    u8 major (0), u8 minor (>= 1), u32 max sections @4, u32 splat count @16,
              u16 compression level @20 (0, 1 or 2), f32 SH min @36 and max @40 (level 2's range;
              0 means the default -1.5 / 1.5)
    section   u32 splat count @0, u32 capacity @4, u32 bucket capacity @8, u32 bucket count @12,
              f32 block size @16, u16 bytes per bucket @20 (12), u32 position range @24 (0: 1 at
              level 0, 32767 otherwise), u32 full buckets @32, u32 partly filled buckets @36,
              u16 SH degree @40
    data      u32 length per partly filled bucket, f32 x3 centre per bucket, then `capacity`
              records of
                  position  level 0: f32 x3; else u16 x3, (u - range) * block / 2 / range from the
                            centre of the splat's bucket (full buckets first, then the partly filled
                            ones in order)
                  scale     linear, f32 x3 (level 0) or half x3
                  rotation  w, x, y, z normalised, f32 (level 0) or half
                  colour    u8 x4: R, G, B = (0.5 + C0 * DC) * 255, A = sigmoid(opacity) * 255
                  SH        band by band, each band's three channels in turn ((2l+1) coefficients
                            each, R then G then B): f32 (level 0), half (1) or u8 spread over
                            [SH min, SH max] (2)
GaussianSplats3D writes SH degrees 0 to 2; a degree-3 section's third band follows the same rule
(as splat-transform reads it). Positions stay as stored (the PLY's axes).
"""

import os

import numpy as np

from ..core import SplatCloud
from ..core import sh as shmod
from ..core.splats import logit
from .common import SplatFileError, apply_nonfinite_policy, check_nonfinite_policy, log_scales_from_linear, warn_notes

HEADER_BYTES = 4096
SECTION_HEADER_BYTES = 1024
BUCKET_BYTES = 12  # a bucket's centre: three float32
SH_RANGE = 1.5  # level 2's SH range when the header leaves it 0
POSITION_RANGE = {0: 1, 1: 32767, 2: 32767}

HEADER = np.dtype(
    {
        "names": ["major", "minor", "max_sections", "splats", "level", "sh_min", "sh_max"],
        "formats": ["u1", "u1", "<u4", "<u4", "<u2", "<f4", "<f4"],
        "offsets": [0, 1, 4, 16, 20, 36, 40],
        "itemsize": HEADER_BYTES,
    }
)
SECTION = np.dtype(
    {
        "names": [
            "splats",
            "capacity",
            "bucket_capacity",
            "buckets",
            "block_size",
            "bucket_bytes",
            "position_range",
            "full_buckets",
            "partial_buckets",
            "sh_degree",
        ],
        "formats": ["<u4", "<u4", "<u4", "<u4", "<f4", "<u2", "<u4", "<u4", "<u4", "<u2"],
        "offsets": [0, 4, 8, 12, 16, 20, 24, 32, 36, 40],
        "itemsize": SECTION_HEADER_BYTES,
    }
)


def record(level: int, sh_degree: int) -> np.dtype:
    """One splat's record at a compression level and SH degree."""
    wide = "<f4" if level == 0 else "<f2"
    sh = {0: "<f4", 1: "<f2", 2: "u1"}[level]
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    fields = [
        ("position", "<f4" if level == 0 else "<u2", 3),
        ("scale", wide, 3),
        ("rotation", wide, 4),
        ("rgba", "u1", 4),
    ]
    return np.dtype(fields + ([("sh", sh, rest)] if rest else []))


def stored_sh_order(sh_degree: int) -> np.ndarray:
    """For the model's (K-1) x 3 higher coefficients, coefficient-major, the index of each in a
    record's SH (band by band, channel-major within a band)."""
    order = []
    for band in range(1, sh_degree + 1):
        start, width = band * band - 1, 2 * band + 1
        order += [3 * start + channel * width + i for i in range(width) for channel in range(3)]
    return np.array(order, np.int64)


def read(path: str | os.PathLike, nonfinite: str = "raise") -> SplatCloud:
    """Read a .ksplat file (compression level 0, 1 or 2; SH degree 0 to 3) into a SplatCloud."""
    check_nonfinite_policy(nonfinite)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise SplatFileError(path, f"cannot open: {exc.strerror or exc}") from None
    header = _header(path, data)
    level = int(header["level"])
    sections = _section_headers(path, data, int(header["max_sections"]))
    notes: list[str] = []
    clouds = []
    offset = HEADER_BYTES + len(sections) * SECTION_HEADER_BYTES
    with np.errstate(invalid="ignore", over="ignore"):
        for index, section in enumerate(sections):
            cloud, offset = _section(path, data, offset, index, section, level, header, notes)
            clouds.append(cloud)
    count = sum(len(c) for c in clouds)
    if count != int(header["splats"]):
        raise SplatFileError(path, f"the header claims {int(header['splats'])} splats, its sections hold {count}")
    warn_notes(path, notes)
    cloud = SplatCloud.concatenate(clouds) if clouds else SplatCloud.empty()
    return apply_nonfinite_policy(path, cloud, nonfinite, "read")


def _header(path, data):
    if len(data) < HEADER_BYTES:
        raise SplatFileError(path, f"{len(data)} bytes is shorter than a .ksplat header ({HEADER_BYTES} bytes)")
    header = data[:HEADER_BYTES].view(HEADER)[0]
    major, minor, level = int(header["major"]), int(header["minor"]), int(header["level"])
    if major != 0 or minor < 1:
        raise SplatFileError(path, f".ksplat version {major}.{minor}; this reader takes 0.1 and later 0.x")
    if level not in POSITION_RANGE:
        raise SplatFileError(path, f"compression level {level}; .ksplat has levels 0, 1 and 2")
    return header


def _section_headers(path, data, count):
    end = HEADER_BYTES + count * SECTION_HEADER_BYTES
    if end > len(data):
        raise SplatFileError(path, f"the header claims {count} sections, more than the file's {len(data)} bytes hold")
    return data[HEADER_BYTES:end].view(SECTION)


def _section(path, data, offset, index, section, level, header, notes):
    """(the section's splats, the offset of the next section's data)."""
    degree, count, capacity = int(section["sh_degree"]), int(section["splats"]), int(section["capacity"])
    where = f"section {index}"
    if degree > 3:
        raise SplatFileError(path, f"{where} claims SH degree {degree}; .ksplat stores degrees 0 to 3")
    if count > capacity:
        raise SplatFileError(path, f"{where} claims {count} splats in room for {capacity}")
    dtype = record(level, degree)
    partial, buckets = int(section["partial_buckets"]), int(section["buckets"])
    bucket_bytes = int(section["bucket_bytes"]) * buckets + 4 * partial
    end = offset + bucket_bytes + dtype.itemsize * capacity
    if end > len(data):
        raise SplatFileError(
            path, f"{where} claims {capacity} splats and {buckets} buckets, beyond the file's {len(data)} bytes"
        )
    records = data[offset + bucket_bytes : offset + bucket_bytes + dtype.itemsize * count].view(dtype)
    if level == 0:
        positions = records["position"]
    else:
        positions = _bucketed_positions(path, data[offset : offset + bucket_bytes], section, records, where, level)
    cloud = SplatCloud(
        positions=positions,
        rotations=records["rotation"].astype(np.float32),
        log_scales=log_scales_from_linear(records["scale"].astype(np.float32), notes),
        opacity_logits=logit(records["rgba"][:, 3] / 255.0),
        sh=_sh(records, degree, level, header),
    )
    return cloud, end


def _bucketed_positions(path, storage, section, records, where, level):
    """Positions of a compressed section: each splat's u16 offsets from its bucket's centre."""
    full, partial, buckets = (int(section[k]) for k in ("full_buckets", "partial_buckets", "buckets"))
    capacity = int(section["bucket_capacity"])
    if buckets and int(section["bucket_bytes"]) != BUCKET_BYTES:
        raise SplatFileError(path, f"{where} stores {int(section['bucket_bytes'])} bytes per bucket, not 12")
    if full + partial > buckets or (full and not capacity):
        raise SplatFileError(
            path, f"{where}: {full} full and {partial} partly filled buckets of {capacity} do not fit its {buckets}"
        )
    lengths = storage[: 4 * partial].view("<u4").astype(np.int64)
    centres = storage[4 * partial :].view("<f4").reshape(buckets, 3).astype(np.float64)
    n, in_full = len(records), min(len(records), full * capacity)
    bucket = np.empty(n, np.int64)
    bucket[:in_full] = np.arange(in_full) // max(capacity, 1)
    if n > in_full:
        ends = full * capacity + np.cumsum(lengths)
        if not partial or ends[-1] < n:
            raise SplatFileError(path, f"{where} holds {n} splats, more than its buckets")
        bucket[in_full:] = full + np.searchsorted(ends, np.arange(in_full, n), side="right")
    span = POSITION_RANGE[level] if int(section["position_range"]) == 0 else int(section["position_range"])
    step = float(section["block_size"]) / 2.0 / span
    return (records["position"].astype(np.float64) - span) * step + centres[bucket]


def _sh(records, degree, level, header):
    """(N, K, 3) SH: the DC from the 8-bit colour, the rest from the record's SH."""
    dc = shmod.rgb_to_dc(records["rgba"][:, :3] / 255.0)[:, None, :]
    if degree == 0:
        return dc
    stored = records["sh"][:, stored_sh_order(degree)].astype(np.float64)
    if level == 2:
        low, high = _sh_bound(header["sh_min"], -SH_RANGE), _sh_bound(header["sh_max"], SH_RANGE)
        stored = low + stored / 255.0 * (high - low)
    return np.concatenate([dc, stored.reshape(len(records), (degree + 1) ** 2 - 1, 3)], axis=1)


def _sh_bound(value, default):
    """A header's SH bound, or the default where it is 0 or NaN (as GaussianSplats3D reads it)."""
    value = float(value)
    return value if value == value and value != 0 else default
