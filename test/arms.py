"""Third-party arm descriptions for tests: example-robot-data's URDFs (PyPI, a test dependency).

``arm_urdf('ur5')`` is the path of that arm's URDF in the installed wheel; ``ARMS`` names the
arms the suite uses. The wheel has no Python module: its files are found through the
distribution's own file list (importlib.metadata, a public API).
"""
from __future__ import annotations

from importlib import metadata
from pathlib import Path

__all__ = ['ARMS', 'arm_urdf', 'robots_dir']

# name: (path below the wheel's robots/ folder, identified joints; None: every movable joint)
ARMS: dict[str, tuple[str, list[str] | None]] = {
    'ur5': ('ur_description/urdf/ur5_robot.urdf', None),
    'ur10': ('ur_description/urdf/ur10_robot.urdf', None),
    'panda': ('panda_description/urdf/panda.urdf', [f'panda_joint{i}' for i in range(1, 8)]),
    'kinova': ('kinova_description/robots/kinova.urdf', None),
    'xarm7': ('xarm_description/urdf/xarm7.urdf', None),
    'z1': ('z1_description/urdf/z1.urdf', None),
    'ur3': ('ur_description/urdf/ur3_robot.urdf', None),
    'so101': ('so_arm_description/urdf/so101.urdf',   # 0.6 kg hobby arm, its gripper locked
              ['shoulder_pan', 'shoulder_lift', 'elbow_flex', 'wrist_flex', 'wrist_roll']),
    # arms on a larger robot, a hand (TIAGo, Talos) or gripper (Baxter) of locked joints
    'talos': ('talos_data/robots/talos_left_arm.urdf',
              [f'arm_left_{i}_joint' for i in range(2, 8)]),
    'tiago': ('tiago_description/robots/tiago.urdf', [f'arm_{i}_joint' for i in range(1, 8)]),
    'tiago_pro': ('tiago_pro_description/robots/tiago_pro.urdf',   # meshes, no SRDF
                  [f'arm_left_{i}_joint' for i in range(1, 8)]),
    'baxter': ('baxter_description/urdf/baxter.urdf',
               ['left_s0', 'left_s1', 'left_e0', 'left_e1', 'left_w0', 'left_w1', 'left_w2']),
    'alex': ('alex_description/urdf/alex_nub_hands.urdf',   # a humanoid's arm, no SRDF
             ['LeftShoulderPitch', 'LeftShoulderRoll', 'LeftShoulderYaw', 'LeftElbowPitch',
              'LeftWristYaw', 'LeftWristRoll', 'LeftGripperYaw']),
}


def robots_dir() -> Path:
    """The robots/ folder of the installed example-robot-data wheel."""
    dist = metadata.distribution('example-robot-data')
    return Path(dist.locate_file('cmeel.prefix/share/example-robot-data/robots'))


def arm_urdf(name: str) -> Path:
    """The URDF of arm ``name`` (a key of ARMS)."""
    path = robots_dir() / ARMS[name][0]
    if not path.is_file():
        raise FileNotFoundError(f'example-robot-data has no {path}')
    return path
