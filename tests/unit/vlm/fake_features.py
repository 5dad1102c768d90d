"""A numpy stand-in for LSeg used by test_vlm_extractor: [16, H/2, W/2]
features from the mean colour of every second pixel, scaled per channel.
slow_features is the same, slower than the frames come: each call appends
the frame's first pixel to $VLFF_TEST_MARK (so the test knows a frame is
being served) and then takes $VLFF_TEST_DELAY_S seconds. odd_huge_features
gives values beyond float16's range for frames whose first byte is odd."""
import os
import time

import numpy as np

D = 16


def features(rgb):
    m = rgb[::2, ::2].astype(np.float64).mean(axis=2) / 255.0
    return np.stack([m * (d + 1) / D for d in range(D)])


def slow_features(rgb):
    mark = os.environ.get("VLFF_TEST_MARK")
    if mark:
        with open(mark, "a") as f:
            f.write(f"{rgb[0, 0, 0]}\n")
    time.sleep(float(os.environ.get("VLFF_TEST_DELAY_S", "1")))
    return features(rgb)


def odd_huge_features(rgb):
    return features(rgb) * (1e6 if rgb[0, 0, 0] % 2 else 1.0)
