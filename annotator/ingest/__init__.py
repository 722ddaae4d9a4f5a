"""Recorded sequences into a moving rig's dataset (``annotator ingest``, FORMAT.md sequences).

:mod:`.sources` opens what a camera's tool wrote: ROS bags (:mod:`.rosbag`, with
:mod:`.ros_image` for their image messages and :mod:`.rosbag1_salvage` for a ROS 1 bag cut
short), Azure Kinect recordings (:mod:`.kinect`), Record3D exports (:mod:`.record3d`),
videos (:mod:`.video`) and folders of colour and depth images as capture tools name them,
each as a :class:`~.recording.Recording`; :mod:`.distortion` brings a recorder's lens model
to OpenCV's, :mod:`.registration` draws depth taken by another camera on the colour camera's
grid, :mod:`.rig` writes the rig a file describes or checks it against the dataset's;
:mod:`.selection` picks every N-th frame and drops those too blurred to read; :mod:`.write`
writes the frames as the dataset stores them and frames.json; :mod:`.scene` runs the whole
(:func:`~.scene.ingest_recording`).
"""
