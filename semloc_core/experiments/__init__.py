"""Experiments: evaluations, calibrations, training and the demo's world, as library code.

Each takes a typed spec (``spec.Spec``: a frozen pydantic model, unknown fields refused) and returns its result;
``semloc`` commands only parse a spec file, a preset and overrides into one, call ``run(spec)`` and write the
report. Nothing here parses a command line, talks to the bus or logs to rerun.

=========================== ======================================================== ==========================
module                      what                                                     command
=========================== ======================================================== ==========================
``loopclosure``             PR of the similarity scores, the engine, the map         ``semloc eval loopclosure``
``localization``            particle filter runs against a dataset's object map      ``semloc eval localization``
``mapping``                 voxel object maps against ground truth, fits, the loop   ``semloc eval mapping``
``detector_calibration``    score likelihoods p(z|d), p(z|not d)                     ``semloc calibrate``
``template_selection``      each class's exemplar views                              ``semloc select-templates``
``detector_training``       the linear window detector                               ``semloc train-detector``
``demo_world``              the demo's cached world and its calibrations             ``semloc demo``
=========================== ======================================================== ==========================

The documented settings ship as presets, ``presets/<kind>/<name>.yaml`` (``spec.preset_file``).
"""
