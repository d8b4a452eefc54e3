"""Constants shared by the synthetic world's modules: hit codes, the pattern, sky,
filter and transient vocabularies, anti-aliasing offsets and colour transforms.
"""

from __future__ import annotations

import numpy as np

NO_HIT = -1


GROUND = -2


PATTERNS = ("stripes", "checker", "bricks", "dots", "noise")


SKIES = ("day", "dusk", "overcast", "night")


FILTERS = ("none", "bw", "sepia")


SHAPES = ("person", "umbrella", "vehicle", "sign")


EPS = 1e-7


# AA sample offsets inside a pixel; the first one is the pixel centre (the truth).
AA_OFFSETS = {
    1: ((0.5, 0.5),),
    5: ((0.5, 0.5), (0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)),
}


LUMA = np.array([0.299, 0.587, 0.114])


SEPIA = np.array([1.07, 0.74, 0.43])
