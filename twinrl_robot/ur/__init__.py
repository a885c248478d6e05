"""A Universal Robots cell: the driver over ur_rtde, its gripper and cameras, and an
emulator of the controller's protocols backed by the plant (:mod:`.emulator`)."""
