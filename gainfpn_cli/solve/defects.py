"""Defective photosites: the kinds a sensor has and their codes.

* ``hot``: collects a dark-current offset on top of its response to light;
* ``dead``: no response to light;
* ``stuck``: one reading whatever the light;
* ``noisy``: readings scattered far more than the noise of its level.

The codes are those of a defect map (0: healthy), as the simulator's truth writes them.
"""

#: Code of a healthy photosite and of each kind of defect.
HEALTHY, HOT, DEAD, STUCK, NOISY = 0, 1, 2, 3, 4
KINDS = {"hot": HOT, "dead": DEAD, "stuck": STUCK, "noisy": NOISY}
