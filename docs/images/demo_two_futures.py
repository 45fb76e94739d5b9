"""Compose docs/images/demo_two_futures.png (the README's picture) from the demo's side_by_side.mp4.

    tesseract4d demo --headless --out /tmp/demo_out
    .venv/bin/python docs/images/demo_two_futures.py /tmp/demo_out/side_by_side.mp4 docs/images/demo_two_futures.png \
        "shove the purple cube 10 cm to the left" "don't move"

Per instruction: RGB at frames 0, 5, 10 and 15, then the depth and normals of frame 15.
"""
import sys
import cv2
import imageio.v3 as iio
import numpy as np

video = iio.imread(sys.argv[1])  # (t, 304, 1536, 3): per future RGB | depth | normals, 256 px each, caption 48 px
labels = sys.argv[3:5]
S, CAP, GAP = 160, 26, 4
rows = []
for k, x0 in enumerate((0, 768)):
    panels = []
    names = []
    for t in (0, 5, 10, 15):
        panels.append(video[t, 48:304, x0:x0 + 256]); names.append(f"RGB, frame {t}")
    panels.append(video[15, 48:304, x0 + 256:x0 + 512]); names.append("depth, frame 15")
    panels.append(video[15, 48:304, x0 + 512:x0 + 768]); names.append("normals, frame 15")
    tiles = []
    for p, n in zip(panels, names):
        tile = cv2.resize(p, (S, S), interpolation=cv2.INTER_AREA)
        band = np.full((18, S, 3), 255, np.uint8)
        cv2.putText(band, n, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (40, 40, 40), 1, cv2.LINE_AA)
        tiles.append(np.concatenate([band, tile], 0))
        tiles.append(np.full((S + 18, GAP, 3), 255, np.uint8))
    strip = np.concatenate(tiles[:-1], 1)
    cap = np.full((CAP, strip.shape[1], 3), 255, np.uint8)
    cv2.putText(cap, f'"{labels[k]}"', (4, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    rows.append(np.concatenate([cap, strip], 0))
img = np.concatenate([rows[0], np.full((8, rows[0].shape[1], 3), 255, np.uint8), rows[1]], 0)
iio.imwrite(sys.argv[2], img, compress_level=9)
print(img.shape)
