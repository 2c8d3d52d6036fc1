"""Motion models of the filter (paper eq. 1-2 and the ground robots' and constant-velocity
alternatives): `ins` (the INS mechanisation, its Jacobians and noise), `models` (the
`MotionModel` protocol and its three implementations), `segments` (motion samples held
between frames)."""
