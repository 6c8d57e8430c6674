"""A run's luminance spread at two scales against the painting's (development aid, CPU).

python benchmarks/tone_spread.py RUN PAINTING
The first 12 views of RUN/renders/ and RUN/originals/ (un-stylized) and the painting resized to the views' height:
the luminance's standard deviation over all pixels, of its Gaussian blur at a twentieth of the height (the
arrangement of light and dark over whole regions) and of the residual (strokes and texture)."""
import glob
import sys

import cv2
import numpy as np


def luma(path: str) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(path), cv2.COLOR_BGR2GRAY).astype(np.float32) / 255.0


def spreads(y: np.ndarray) -> tuple:
    coarse = cv2.GaussianBlur(y, (0, 0), y.shape[0] / 20.0)
    return float(y.std()), float(coarse.std()), float((y - coarse).std())


def main(run: str, painting: str) -> None:
    rows = {}
    for name in ("renders", "originals"):
        files = sorted(glob.glob(f"{run}/{name}/view_*.png"))[:12]
        if not files:
            sys.exit(f"{run}/{name}: no views")
        rows[name] = np.mean([spreads(luma(f)) for f in files], 0)
    h = luma(sorted(glob.glob(f"{run}/renders/view_*.png"))[0]).shape[0]
    p = luma(painting)
    p = cv2.resize(p, (int(round(p.shape[1] * h / p.shape[0])), h), interpolation=cv2.INTER_AREA)
    rows["painting"] = spreads(p)
    print("| images | all | coarse | fine |\n| --- | --- | --- | --- |")
    for name, (a, c, f) in (("stylized (renders)", rows["renders"]), ("un-stylized (originals)", rows["originals"]),
                            ("the painting", rows["painting"])):
        print(f"| {name} | {a:.3f} | {c:.3f} | {f:.3f} |")


if __name__ == "__main__":
    main(*sys.argv[1:3])
