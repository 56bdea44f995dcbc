"""A survey posed by the camera alone, and the map built at those poses.

In the order ``nap3d-graph map`` runs them: :mod:`.survey` (frame-to-frame odometry, the
longest tracked segment, keyframes), :mod:`.retrieval` (a global descriptor per keyframe for
loop candidates by appearance), :mod:`.loops` (candidates by appearance and proximity, each
verified with NAP3D's own aligner real-vs-real), :mod:`.pose_graph` (the robust pose graph in
GTSAM: GNC drops what does not agree), :mod:`.bundle` (the refinement over every verified
match's 3D points), :mod:`.build` (the stages, resumable, and the field trained at the
poses; :mod:`.folder` names the map folder's files, :mod:`.report` writes its outputs);
:mod:`.verification` is what "verified" means for loops and relocalisation; :mod:`.posed` presents a sequence with the map's poses as if they were its own;
:mod:`.relocalise` finds a frame in a map.
"""
