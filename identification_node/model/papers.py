"""Tables of the two papers the method comes from (shared/seeds), transcribed once.

An, Atkeson, Hollerbach (1986), MIT Serial Link Direct Drive Arm: Table 1 (CAD parameters; the
bundled mit_dd_arm URDF carries them) and Table 3 (identifiable linear combinations with
l2 = 0.45 m, subscripts decoded from the OCR text; the paper's estimate and CAD columns).
"""

# Table 1: per link [m, mx, my, mz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz] (kg, kg m, kg m^2).
MIT_TABLE1 = (
    (67.13, 0.0, 2.432, 35.8257, 23.1568, 0.0, -0.3145, 20.4472, -1.2948, 0.7418),
    (53.01, 0.0, 3.4081, 16.6505, 7.9088, 0.0, 0.0, 7.6766, -1.5036, 0.6807),
    (19.67, 0.3108, 0.0, 0.3268, 0.1825, 0.0, -0.0166, 0.4560, 0.0, 0.3900),
)

# Table 3: (combination, paper's estimate, paper's CAD value). The CAD value of
# link3.Ixx - link3.Iyy is a typo in the paper: Table 1 gives -0.2735.
MIT_TABLE3 = (
    ({'link2.Iyz': 1.0, 'link3.mz': 0.45}, -1.0589, -1.3565),
    ({'link3.Ixx': 1.0, 'link3.Iyy': -1.0}, -0.3691, -0.2702),
    ({'link2.Izz': 1.0, 'link3.Ixx': 1.0}, 0.7082, 0.8632),
    ({'link1.Izz': 1.0, 'link2.Ixx': 1.0, 'link3.Ixx': 1.0, 'link3.m': 0.45 ** 2},
     15.7029, 12.8169),
    ({'link2.Ixx': 1.0, 'link2.Iyy': -1.0, 'link3.Ixx': 1.0}, 0.4709, 0.4147),
    ({'link3.mz': 1.0, 'link2.my': -1.0}, -1.6863, -3.0814),
)
