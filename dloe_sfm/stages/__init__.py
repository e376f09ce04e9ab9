"""The command line's stages, one module each (``dloe-sfm <stage>`` or
``python -m dloe_sfm.stages.<stage>``), each with ``configure_parser(parser)``, ``run(args)``
and a ``main(...)`` callable from Python:

- ``solve``: run DLOE on a capture file and write a result file;
- ``reconstruct``: keypoints on a COLMAP workspace -> the outputs folder;
- ``simulate``: an unsynchronised capture of a mocap sequence;
- ``demo``: the whole chain on the bundled demo workspace, scored against the known truth;
- ``import_calibration``: a calibration made elsewhere -> a COLMAP model;
- ``view``: play a ``reconstruct`` output in open3d's window (or write a GIF);
- ``evaluate``: score a result against ground truth (the scoring itself: ``dloe_sfm.evaluate``);
- ``benchmark``: the paper's experiments with every baseline;
- ``sync``: each stream's time offset and rate of an output;
- ``batch``: many captures / COLMAP workspaces as Dask tasks (``dloe_sfm.batch``).
"""
