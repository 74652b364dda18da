"""The .usdz package of one layer, as OpenUSD writes it."""

import os
import shutil
import zipfile

USDZ_ALIGN = 64


def write_usdz(path, name, layer):
    """A .usdz of one layer (bytes, or the name of a file holding them) named `name` inside: stored
    uncompressed, its data starting on a 64-byte boundary (the package format's rule, so readers
    can map it in place). A file is copied in chunks, never held in memory whole."""
    size = len(layer) if isinstance(layer, bytes) else os.path.getsize(layer)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED, allowZip64=True) as z:
        info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
        info.file_size = size
        header = 30 + len(name.encode())
        pad = -(header + 4) % USDZ_ALIGN
        info.extra = b"\x86\x19" + pad.to_bytes(2, "little") + b"\0" * pad  # a private padding field
        with z.open(info, "w") as out:
            if isinstance(layer, bytes):
                out.write(layer)
            else:
                with open(layer, "rb") as f:
                    shutil.copyfileobj(f, out, 1 << 20)
