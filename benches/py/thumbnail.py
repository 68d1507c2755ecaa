"""The peer of benches/thumbnails.rs: Pillow making the same thumbnails (decode, shrink the long
side to 160 px, JPEG quality 80). Prints the median seconds of `reps` passes over the files."""
import io
import statistics
import sys
import time

from PIL import Image


def thumbnail(data: bytes) -> bytes:
    img = Image.open(io.BytesIO(data)).convert("RGB")
    img.thumbnail((160, 160), Image.Resampling.BOX)
    out = io.BytesIO()
    img.save(out, "JPEG", quality=80)
    return out.getvalue()


def main() -> None:
    reps, files = int(sys.argv[1]), sys.argv[2:]
    data = [open(f, "rb").read() for f in files]
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        for d in data:
            thumbnail(d)
        times.append(time.perf_counter() - t)
    print(statistics.median(times))


if __name__ == "__main__":
    main()
