"""Motion capture: real systems' clients, a protocol-level simulator, per-body filtering.

See ``docs/mocap.md``. One mocap process per experiment (:mod:`.process`) holds the single
connection to the mocap server and publishes each rigid body's pose on the bus
(``hilswarm/<exp>/mocap/<body>``, :mod:`.message`); each agent reads only its own body
(:mod:`.pose_source`). Every pose is in the project's world frame (:mod:`.frames`).
"""
