"""newtsim's application: the jobs a user runs on the observation model (:mod:`scenes`).

* :mod:`.render`     a scene to a FITS frame (the sources, the sensor chain, the truth extensions)
* :mod:`.batch`      many frames on Dask: sweeps, time sequences, Monte-Carlo draws; resumable
* :mod:`.compare`    the model against a measured frame; diagnosis of the missing effect; ``--apply``
* :mod:`.quicklook`  PNG quick-looks of frames
* :mod:`.cli`        the ``newtsim`` command line, one module per command group
"""
