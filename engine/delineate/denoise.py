"""Non-local means denoising with OpenCV (Buades, Coll & Morel 2005; MATHS §3).

OpenCV rather than scikit-image: about 3× faster at equal settings, which matters on 8–24 MP photos.
Parameters are in OpenCV's units (h in grey levels of an 8-bit image), so values quoted by papers that
used OpenCV carry over; MATHS §3 gives the mapping to skimage.restoration.denoise_nl_means.
"""

from __future__ import annotations

import cv2
import numpy as np

from engine.delineate.params import check
from engine.errors import InputError


def denoise(image: np.ndarray, *, h: float = 4.0, h_color: float = 10.0, template_window: int = 7,
            search_window: int = 21) -> np.ndarray:
    """Non-local means of an 8-bit grey (H, W) or RGB (H, W, 3) photo; same shape and dtype back.

    h : filter strength for grey levels (luminance for colour), in 0–255 units; larger removes more noise
        and more detail. h_color : the same for the colour (a*, b*) channels of a colour photo.
    template_window, search_window : patch side and search-window side, px (odd).
    Colour photos are filtered in CIELab by cv2.fastNlMeansDenoisingColored.
    """
    for field_name, value, name in (("nlm_h", h, "h"), ("nlm_h", h_color, "h_color"),
                                    ("nlm_template", template_window, "template_window"),
                                    ("nlm_search", search_window, "search_window")):
        check(field_name, value, name)
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise InputError(None, f"denoise needs an 8-bit photo (uint8); got {image.dtype}")
    if image.ndim == 2:
        return cv2.fastNlMeansDenoising(image, None, float(h), int(template_window), int(search_window))
    if image.ndim == 3 and image.shape[2] == 3:
        bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)  # OpenCV's Lab conversion expects BGR order
        out = cv2.fastNlMeansDenoisingColored(bgr, None, float(h), float(h_color), int(template_window),
                                              int(search_window))
        return cv2.cvtColor(out, cv2.COLOR_BGR2RGB)
    raise InputError(None, f"denoise needs a grey (H, W) or RGB (H, W, 3) photo; got shape {image.shape}")
