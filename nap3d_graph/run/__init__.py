"""The drift-correction run, stage by stage.

``pipeline`` (the loop: :class:`~nap3d_graph.run.pipeline.Pipeline`, a frame at a time in
``step``), ``graph`` (the keyframe graph in iSAM2: the gate, the window, the final solve),
``motion`` (the motion model between keyframes; ``imu`` the IMU's), ``selection`` (which
frames are keyframes), ``keyframe`` (one
keyframe's NAP3D measurement, inline or on a worker), ``solve`` (iSAM2 parameters, the
rebuild after a failed update, GNC), ``chain`` (frames chained from keyframes), ``config``
(what a run is told), ``records`` (what it gives back), ``output`` (the results folder),
``live`` (:class:`~nap3d_graph.run.live.DriftCorrector`, the run a frame at a time for your
own loop), ``default`` (the embedded default's data and field), ``bag`` and ``viz`` (a run as
a ROS bag and as a rerun recording).
"""
