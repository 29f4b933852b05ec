"""detect stage of tsnav: per-state, per-class detection tables (DESIGN.md "Detector", paper III-B / Fig. 2).

* :mod:`.table`     the ``detections_<name>.hdf5`` format, :func:`load_detections`, :func:`install_detections`
* :mod:`.oracle`    ground truth from the renderer's instance ids and the oracle detector
* :mod:`.model`     the learned dense grid detector (FCOS-like, for 64x64 frames)
* :mod:`.data`      training frames and targets
* :mod:`.train`     training, checkpoints, temperature scaling
* :mod:`.learned`   the learned detector's tables
* :mod:`.evaluate`  per-class AP and reliability tables
* :mod:`.command`   ``tsnav detect``

Heavy dependencies (torch) load only with the modules that need them.
"""

from .table import (Detections, detections_path, install_detections, load_detections, load_scene_detections,
                    write_detections)

__all__ = ["Detections", "detections_path", "install_detections", "load_detections", "load_scene_detections",
           "write_detections"]
