"""Detection in tsnav: per-state, per-class detection tables (DESIGN.md "Detector", paper III-B / Fig. 2).

The table's file format (``detections_<name>.hdf5``) belongs to the data layer: :mod:`tsnav.data.detections`;
:meth:`tsnav.sim.batch.SceneBank.install_detections` puts it into a bank.

* :mod:`.oracle`    ground truth from the renderer's instance ids and the oracle detector
* :mod:`.model`     the learned dense grid detector (FCOS-like, for 64x64 frames)
* :mod:`.data`      training frames and targets
* :mod:`.train`     training, checkpoints, temperature scaling
* :mod:`.learned`   the learned detector's tables
* :mod:`.evaluate`  per-class AP and reliability tables
* :mod:`.registry`  the detectors by name (oracle, learned, shipped): how each is opened and writes its tables
* :mod:`.command`   ``tsnav detect`` (its `--detector` choices are the registry's)

Heavy dependencies (torch) load only with the modules that need them.
"""
