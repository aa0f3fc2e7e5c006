"""Which JPEG encoder for a camera's ``sensor_msgs/msg/CompressedImage``: time and bytes, one run.

Issue 41 asks for the encoder to be chosen by a measurement: a 640x480 RGB frame (the simulated
camera's: a gradient with noise and moving bars, closer to a real scene than random pixels,
which no JPEG compresses) encoded at quality 80 and decoded again by every candidate that is
importable, all with 4:2:0 chroma subsampling (the JPEG default of Pillow and OpenCV): Pillow
(libjpeg-turbo in its wheels), simplejpeg (libjpeg-turbo, made for this),
OpenCV (``opencv-python-headless``) and imagecodecs. It prints milliseconds per encode and per
decode (median of ``--repeats`` runs of ``--n``), the JPEG's bytes, and each one's ratio to
Pillow's encode time, the baseline every Python install with arpz's server extra has.

Run: ``python benchmarks/image_encoders.py`` (``--json PATH`` for the figures). A candidate that
is not installed is named and left out.
"""

from __future__ import annotations

import argparse
import io
import json
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

WIDTH, HEIGHT = 640, 480


def camera_frame(seed: int = 1) -> np.ndarray:
    """A 640x480 RGB frame shaped like a scene: gradients, edges and sensor noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    frame = np.stack([x * 255 // WIDTH, y * 255 // HEIGHT, (x + y) * 255 // (WIDTH + HEIGHT)], -1)
    frame[(x // 80) % 2 == 0] //= 2
    noise = rng.normal(0, 6, frame.shape)
    return np.clip(frame + noise, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Encoder:
    name: str
    encode: Callable[[np.ndarray, int], bytes]
    decode: Callable[[bytes], np.ndarray]


def encoders() -> tuple[list[Encoder], list[str]]:
    found: list[Encoder] = []
    missing: list[str] = []
    try:
        from PIL import Image

        def pil_encode(frame: np.ndarray, quality: int) -> bytes:
            out = io.BytesIO()
            Image.fromarray(frame).save(out, format="JPEG", quality=quality)
            return out.getvalue()

        def pil_decode(data: bytes) -> np.ndarray:
            return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

        found.append(Encoder("Pillow", pil_encode, pil_decode))
    except ImportError:
        missing.append("Pillow")
    try:
        import simplejpeg

        found.append(
            Encoder(
                "simplejpeg",
                lambda frame, quality: simplejpeg.encode_jpeg(
                    frame, quality=quality, colorsubsampling="420"
                ),
                lambda data: simplejpeg.decode_jpeg(data),
            )
        )
    except ImportError:
        missing.append("simplejpeg")
    try:
        import cv2

        def cv_encode(frame: np.ndarray, quality: int) -> bytes:
            ok, data = cv2.imencode(
                ".jpg", frame[:, :, ::-1], [int(cv2.IMWRITE_JPEG_QUALITY), quality]
            )
            assert ok
            return bytes(data)

        found.append(
            Encoder(
                "OpenCV",
                cv_encode,
                lambda data: cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[
                    :, :, ::-1
                ],
            )
        )
    except ImportError:
        missing.append("opencv-python-headless")
    try:
        import imagecodecs

        found.append(
            Encoder(
                "imagecodecs",
                lambda frame, quality: bytes(imagecodecs.jpeg_encode(frame, level=quality)),
                lambda data: imagecodecs.jpeg_decode(data),
            )
        )
    except ImportError:
        missing.append("imagecodecs")
    return found, missing


def median_ms(call: Callable[[], Any], n: int, repeats: int) -> float:
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(n):
            call()
        runs.append((time.perf_counter() - start) / n * 1e3)
    return statistics.median(runs)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=30, help="encodes per run")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quality", type=int, default=80)
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    frame = camera_frame()
    found, missing = encoders()
    print(f"a {WIDTH}x{HEIGHT} RGB frame ({frame.nbytes} bytes raw), JPEG quality {args.quality}")
    print(f"{'encoder':12} {'bytes':>8} {'encode ms':>10} {'decode ms':>10} {'x Pillow':>9}")
    rows = []
    base = 0.0
    for encoder in found:
        data = encoder.encode(frame, args.quality)
        back = encoder.decode(data)
        error = float(np.abs(back.astype(int) - frame.astype(int)).mean())
        encode_ms = median_ms(lambda e=encoder: e.encode(frame, args.quality), args.n, args.repeats)
        decode_ms = median_ms(lambda e=encoder, d=data: e.decode(d), args.n, args.repeats)
        base = base or encode_ms
        ratio = encode_ms / base
        print(
            f"{encoder.name:12} {len(data):8} {encode_ms:10.2f} {decode_ms:10.2f} {ratio:9.2f}"
            f"   (mean abs error {error:.1f})",
            flush=True,
        )
        rows.append(
            {
                "encoder": encoder.name,
                "bytes": len(data),
                "encode_ms": encode_ms,
                "decode_ms": decode_ms,
                "ratio_to_pillow": ratio,
                "mean_abs_error": error,
            }
        )
    if missing:
        print("not installed here, left out: " + ", ".join(missing))
    if args.json:
        with open(args.json, "w") as out:
            json.dump(rows, out, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
