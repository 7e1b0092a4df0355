"""``thumbnail.png``: the corrected depth and the flags side by side over a colour key, drawn without matplotlib.

The default output level writes a thumbnail of every scan; importing matplotlib for it would cost a one-scan
correction 0.35 s of start-up. The image is a colour lookup, written as a PNG by Pillow.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mpi_lidar.correction import Correction, Flag
from mpi_lidar.reporting.legend import FLAG_COLOURS as FLAG_COLOURS  # the registry's, re-exported
from mpi_lidar.scans.scan import Scan

KEY_ROW_PX = 14  # one line of the colour key under the panels [px]
THUMBNAIL_PX = 512  # longest side of thumbnail.png [px]
THUMBNAIL_GAP_PX = 4
THUMBNAIL_ZOOM = 8  # most times a small scan's pixel is repeated in the thumbnail
# matplotlib's viridis, its 256 colours as RGB bytes (tests/reporting/test_thumbnail.py checks them against it).
VIRIDIS_RGB = np.frombuffer(bytes.fromhex(
    '44015444025544035745055845065a45085b46095c460b5e460c5f460e61470f6247116347126547146647156747166947186a48196b481a'
    '6c481c6e481d6f481e70482071482172482273482374472575472676472777472878472a79472b7a472c7b462d7c462f7c46307d46317e45'
    '327f45347f453580453681443781443982433a83433b83433c84423d84423e854240854141864142864043874044873f45873f47883e4888'
    '3e49893d4a893d4b893d4c893c4d8a3c4e8a3b508a3b518a3a528b3a538b39548b39558b38568b38578c37588c37598c365a8c365b8c355c'
    '8c355d8c345e8d345f8d33608d33618d32628d32638d31648d31658d31668d30678d30688d2f698d2f6a8d2e6b8e2e6c8e2e6d8e2d6e8e2d'
    '6f8e2c708e2c718e2c728e2b738e2b748e2a758e2a768e2a778e29788e29798e287a8e287a8e287b8e277c8e277d8e277e8e267f8e26808e'
    '26818e25828e25838d24848d24858d24868d23878d23888d23898d22898d228a8d228b8d218c8d218d8c218e8c208f8c20908c20918c1f92'
    '8c1f938b1f948b1f958b1f968b1e978a1e988a1e998a1e998a1e9a891e9b891e9c891e9d881e9e881e9f881ea0871fa1871fa2861fa38620'
    'a48520a58521a68521a78422a78423a88323a98224aa8225ab8126ac8127ad8028ae7f29af7f2ab07e2bb17d2cb17d2eb27c2fb37b30b47a'
    '32b57a33b67935b77836b87738b97639b9763bba753dbb743ebc7340bd7242be7144be7045bf6f47c06e49c16d4bc26c4dc26b4fc36951c4'
    '6853c56755c66657c66559c7645bc8625ec96160c96062ca5f64cb5d67cc5c69cc5b6bcd596dce5870ce5672cf5574d05477d05279d1517c'
    'd24f7ed24e81d34c83d34b86d44988d5478bd5468dd64490d64392d74195d73f97d83e9ad83c9dd93a9fd938a2da37a5da35a7db33aadb32'
    'addc30afdc2eb2dd2cb5dd2bb7dd29bade27bdde26bfdf24c2df22c5df21c7e01fcae01ecde01dcfe11cd2e11bd4e11ad7e219dae218dce2'
    '18dfe318e1e318e4e318e7e419e9e419ece41aeee51bf1e51cf3e51ef6e61ff8e621fae622fde724'
), dtype=np.uint8).reshape(256, 3)


def viridis(scaled: np.ndarray) -> np.ndarray:
    """RGB bytes (..., 3) of values in [0, 1], as matplotlib's ``colormaps["viridis"](scaled, bytes=True)``."""
    return VIRIDIS_RGB[np.clip((scaled * 256).astype(np.int64), 0, 255)]


def azimuth_rises(scan: Scan) -> bool:
    """Whether the scan's azimuth grows along its columns (its rays turn towards +x, the scanner's left), from its
    azimuths or, given only ray directions, from its middle row's first and last rays. The thumbnail and the maps
    against pixel columns then run its columns right to left, so that the scanner's left is on the left, as the
    maps in degrees show it. False where the scan has no geometry: nothing says which way it runs."""
    h, w = scan.shape
    if scan.azimuth_rad is not None and np.size(scan.azimuth_rad) == w and w > 1:
        azimuth = np.asarray(scan.azimuth_rad, dtype=np.float64)
        return bool(azimuth[-1] > azimuth[0])
    if scan.ray_directions is not None and w > 1:
        middle = np.asarray(scan.ray_directions[h // 2, [0, -1], 0], dtype=np.float64)
        return bool(middle[1] > middle[0])
    return False


def thumbnail_image(correction: Correction, limit: int = THUMBNAIL_PX,
                    mirror: bool = False) -> tuple[np.ndarray, tuple[float, float]]:
    """RGB image (h, w, 3) uint8, at most ``limit`` pixels on its longest side: the corrected depth (left,
    viridis between its 1 and 99 % quantiles, invalid pixels white) and the flags (right, :data:`FLAG_COLOURS`),
    every ``step``-th pixel of each, or each pixel repeated as often as fits (up to :data:`THUMBNAIL_ZOOM` times)
    where the scan is small. ``mirror``: columns right to left (a scan whose azimuth grows along its columns
    shows the scanner's left on the left, as seen from behind it). Returns the image and the depth range of the
    colours [m]."""
    h, w = correction.flags.shape
    panel = max(1, (limit - THUMBNAIL_GAP_PX) // 2)
    step = max(1, -(-h // limit), -(-w // panel))
    zoom = max(1, min(THUMBNAIL_ZOOM, limit // h, panel // w)) if step == 1 else 1
    columns = slice(None, None, -step) if mirror else slice(None, None, step)
    depth, flags = correction.depth[::step, columns], correction.flags[::step, columns]
    if zoom > 1:
        depth, flags = (np.repeat(np.repeat(a, zoom, axis=0), zoom, axis=1) for a in (depth, flags))
    finite = depth[np.isfinite(depth)]
    low, high = (float(v) for v in np.quantile(finite, [0.01, 0.99])) if finite.size else (0.0, 1.0)
    scaled = np.clip((np.nan_to_num(depth, nan=low) - low) / max(high - low, 1e-9), 0.0, 1.0)
    left = viridis(scaled)
    left[~np.isfinite(depth)] = 255
    palette = np.array([[int(c[i:i + 2], 16) for i in (1, 3, 5)] for c in FLAG_COLOURS], dtype=np.uint8)
    right = palette[np.minimum(flags, len(FLAG_COLOURS) - 1)]
    ph, pw = flags.shape
    image = np.full((ph, 2 * pw + THUMBNAIL_GAP_PX, 3), 255, dtype=np.uint8)
    image[:, :pw], image[:, pw + THUMBNAIL_GAP_PX:] = left, right
    return image, (low, high)


def with_key(image: np.ndarray, flags: np.ndarray, depth_limits: tuple[float, float]) -> np.ndarray:
    """``image`` over a colour key: the depth scale (viridis, its limits in metres) and a swatch and name for every
    flag the scan has, as many per line as fit the image's width."""
    from PIL import Image, ImageDraw  # imported where used, as in write_png

    present = [flag for flag in Flag if (flags == flag).any()]
    width = max(image.shape[1], 220)
    per_line = max(1, width // 110)
    lines = 1 + -(-len(present) // per_line)
    canvas = Image.new("RGB", (width, image.shape[0] + KEY_ROW_PX * lines + 4), "white")
    canvas.paste(Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8)), (0, 0))
    draw = ImageDraw.Draw(canvas)
    top = image.shape[0] + 2
    bar = viridis(np.linspace(0.0, 1.0, 60))[None].repeat(KEY_ROW_PX - 4, axis=0)
    canvas.paste(Image.fromarray(np.ascontiguousarray(bar)), (2, top + 2))
    draw.text((66, top), f"depth {depth_limits[0]:.2f} - {depth_limits[1]:.2f} m", fill="black")
    for i, flag in enumerate(present):
        x, y = 2 + (i % per_line) * 110, top + KEY_ROW_PX * (1 + i // per_line)
        draw.rectangle((x, y + 2, x + 9, y + KEY_ROW_PX - 3), fill=FLAG_COLOURS[flag], outline="black")
        draw.text((x + 13, y), flag.name.lower().replace("_", " "), fill="black")
    return np.asarray(canvas)


def thumbnail_legend(depth_limits: tuple[float, float]) -> str:
    return (f"Thumbnail: corrected depth (left; viridis from {depth_limits[0]:.3f} to {depth_limits[1]:.3f} m, "
            "pixels without a depth white) and what was done per pixel (right); the key is under the panels.")


def write_png(path: Path, image: np.ndarray) -> None:
    """An RGB image (h, w, 3) uint8 as an 8-bit RGB PNG at ``path``."""
    from PIL import Image  # imported where used: only the levels that write a thumbnail pay for it

    Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8)).save(path, format="PNG")
