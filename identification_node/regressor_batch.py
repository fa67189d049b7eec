"""Joint-torque regressor of a pinocchio model for many samples at once (numpy Newton-Euler).

The same Y as pinocchio's ``computeJointTorqueRegressor`` (standard parameters per body about
its joint frame origin, in that frame), computed for N samples together instead of one call
per sample. Kinematics come from the pinocchio model: parents, ``jointPlacements`` and each
joint's motion subspace (revolute, continuous or prismatic, about or along any axis), gravity
``model.gravity``. Each body is handled in its *axis frame*: the joint frame rotated so the
joint axis is z (the rotation is constant), which makes the joint motion a plain z rotation or
z translation; its kinematic vectors are rotated back to the joint frame for the parameters.

Per body c, in its axis frame: angular velocity w, angular acceleration wd and the classical
acceleration a of the frame origin minus gravity (forward recursion, base to tip); every
ancestor-or-self joint i's motion subspace u_i = (ul, ua) expressed at c (motion transform,
same recursion); then Y[i, block c] = ul . f + ua . n for the body wrench
f = m a + wd x mc + w x (w x mc), n = mc x a + I wd + w x (I w), linear in the parameters:
m: ul . a; mc: ul x wd + w (ul . w) - ul |w|^2 + a x ua; I: B(ua, wd) + B(ua x w, w) with
B(x, y) = x' I y.
"""
from __future__ import annotations

import threading
from typing import Sequence

import numpy as np
import pinocchio as pin

_REVOLUTE = {'JointModelRX', 'JointModelRY', 'JointModelRZ', 'JointModelRUBX', 'JointModelRUBY',
             'JointModelRUBZ', 'JointModelRevoluteUnaligned',
             'JointModelRevoluteUnboundedUnaligned'}
_PRISMATIC = {'JointModelPX', 'JointModelPY', 'JointModelPZ', 'JointModelPrismaticUnaligned'}
# Samples per pass (at most), and the size of temporaries (elements) to stay under: glibc
# serves larger ones by mmap, page-faulting afresh on every call.
_CHUNK = 512
_TEMP_ELEMENTS = 14000


def _joint_kind(model: pin.Model, data: pin.Data, j: int) -> tuple[str, np.ndarray] | None:
    """('R' for revolute or continuous, or 'P' for prismatic, unit axis in the joint frame),
    or None for any other joint."""
    name = model.joints[j].shortname()
    if name not in _REVOLUTE and name not in _PRISMATIC:
        return None
    S = np.asarray(data.joints[j].S, dtype=float).reshape(6)
    lin, ang = S[:3], S[3:]
    if name in _REVOLUTE and not lin.any() and np.isclose(np.linalg.norm(ang), 1.0):
        return 'R', ang
    if name in _PRISMATIC and not ang.any() and np.isclose(np.linalg.norm(lin), 1.0):
        return 'P', lin
    return None


def supports(model: pin.Model) -> bool:
    """Whether every joint of ``model`` is revolute, continuous or prismatic."""
    data = model.createData()
    return all(_joint_kind(model, data, j) is not None for j in range(1, model.njoints))


def _axis_frame(axis: np.ndarray) -> np.ndarray:
    """A rotation whose third column is the unit ``axis`` (identity when axis is z)."""
    axis = axis / np.linalg.norm(axis)
    if np.array_equal(axis, [0.0, 0.0, 1.0]):
        return np.eye(3)
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    x = np.cross(helper, axis)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(axis, x), axis])


def _rotate(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R @ v for vectors v (g, 3, ...): einsum's loop sums each entry alike for every batch
    size (BLAS might not)."""
    return np.einsum('rc,gc...->gr...', R, v)


def _skew(v: np.ndarray) -> np.ndarray:
    """[v x] (3, 3)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


class BatchRegressor:
    """Joint-torque regressor of ``model`` (revolute, continuous and prismatic joints only).

    ``joint_ids``: every joint of the model, in the order of the output's rows and parameter
    blocks. ``__call__(q, qd, qdd)`` with (N, n) joint positions (angles also for continuous
    joints), velocities and accelerations in that order returns Y (N, n, 10 n): block c holds
    [m, mx, my, mz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz] of joint c's body about its joint frame origin,
    in that frame (SI units).
    """

    def __init__(self, model: pin.Model, joint_ids: Sequence[int]):
        ids = [int(j) for j in joint_ids]
        if sorted(ids) != list(range(1, model.njoints)):
            raise ValueError('joint_ids must list every joint of the model once')
        data = model.createData()
        user = {j: i for i, j in enumerate(ids)}
        self.n = len(ids)
        self.gravity = np.array(model.gravity.linear, dtype=float)
        # Work array Z (6, width, N) of spatial motion vectors (linear; angular), per body a
        # stack [velocity, acceleration - gravity, subspaces of its ancestors-or-self]; the
        # universe's stack [0, -gravity] comes first.
        frames = {0: np.eye(3)}
        stacks = {0: (0, [])}  # joint id -> (first column of its stack, ancestors-or-self)
        width = 2
        self.bodies = []
        for j in range(1, model.njoints):
            found = _joint_kind(model, data, j)
            if found is None:
                raise ValueError(f'joint {model.names[j]} ({model.joints[j].shortname()}) is '
                                 'not revolute, continuous or prismatic')
            kind, axis = found
            Ra = frames[j] = _axis_frame(axis)
            parent = int(model.parents[j])
            M0 = model.jointPlacements[j]
            ET = (frames[parent].T @ M0.rotation @ Ra).T
            t0 = frames[parent].T @ M0.translation
            X0 = np.zeros((6, 6))   # motion transform parent -> child at q = 0
            X0[:3, :3] = X0[3:, 3:] = ET
            X0[:3, 3:] = -ET @ _skew(t0)
            src, chain = stacks[parent]
            size = 2 + len(chain)
            stacks[j] = (width, chain + [j])
            self.bodies.append((user[j], kind == 'R', X0, src, size, width))
            width += size + 1
        self.width = width
        first = {j: stacks[j][0] for j in stacks}
        self.vel = np.array([first[j] for j in range(1, model.njoints)])
        self.pair_u = np.concatenate([first[j] + 2 + np.arange(len(stacks[j][1]))
                                      for j in range(1, model.njoints)])
        self.pair_body = np.concatenate([np.full(len(stacks[j][1]), j - 1)
                                         for j in range(1, model.njoints)])
        self.pair_rows = np.concatenate([[user[i] for i in stacks[j][1]]
                                         for j in range(1, model.njoints)])
        self.pair_cols = 10 * np.array([user[j + 1] for j in self.pair_body])[:, None] + \
            np.arange(10)
        self._local = threading.local()  # work arrays, per thread
        # bodies whose axis frame is not their joint frame: (index, rotation, their pairs)
        self.tilted = [(j - 1, frames[j], self.pair_body == j - 1) for j in range(1, model.njoints)
                       if not np.array_equal(frames[j], np.eye(3))]

    @property
    def num_pairs(self) -> int:
        return len(self.pair_u)

    def __getstate__(self) -> dict:  # picklable: the per-thread work arrays are not kept
        return {k: v for k, v in self.__dict__.items() if k != '_local'}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._local = threading.local()

    def __call__(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray,
                 out: np.ndarray | None = None) -> np.ndarray:
        """Y (N, n, 10 n) for (N, n) arrays in joint_ids order; written into ``out`` if given
        (only its first 10 n columns)."""
        N, n = q.shape
        if out is None:
            out = np.empty((N, n, 10 * n))
        # Chunks of C samples: temporaries of (pairs, C) stay below ~128 kB (heap, not mmap).
        C = max(16, min(_CHUNK, 1 << max(N - 1, 1).bit_length(),
                        1 << max(_TEMP_ELEMENTS // self.num_pairs, 1).bit_length() - 1))
        work = self._work(C)
        X = work[0]
        for k in range(0, N, C):
            m = min(C, N - k)
            X[0, :, :m], X[1, :, :m], X[2, :, :m] = q[k:k + m].T, qd[k:k + m].T, qdd[k:k + m].T
            if m < C:
                X[:, :, m:] = 0.0
            Yp = self._chunk(*work)
            block = out[k:k + m]
            block[:, :, :10 * n] = 0.0
            block[:, self.pair_rows[:, None], self.pair_cols] = Yp[:, :, :m].transpose(2, 1, 0)
        return out

    def _work(self, C: int) -> tuple[np.ndarray, ...]:
        """Work arrays for chunks of C samples, per thread, made once."""
        cache = self._local.__dict__.setdefault('work', {})
        if C not in cache:
            nb, P = len(self.vel), self.num_pairs
            X = np.zeros((3, self.n, C))
            Z = np.empty((6, self.width, C))
            Z[:, 0] = 0.0   # the universe: at rest, acceleration -gravity
            Z[:3, 1] = -self.gravity[:, None]
            Z[3:, 1] = 0.0
            for _, revolute, _, _, size, dst in self.bodies:  # each joint's own subspace
                Z[:, dst + size] = 0.0
                Z[5 if revolute else 2, dst + size] = 1.0
            cache[C] = (X, Z, np.empty((10, nb, C)), np.empty((10, P, C)),
                        np.empty((6, P, C)), np.empty((10, P, C)))
        return cache[C]

    def _chunk(self, X: np.ndarray, Z: np.ndarray, Kb: np.ndarray, K: np.ndarray,
               U: np.ndarray, Yp: np.ndarray) -> np.ndarray:
        """Y of one chunk as (10 parameters, pairs, C samples), from X = (q, qd, qdd) rows."""
        for col, revolute, X0, src, size, dst in self.bodies:
            x, xd, xdd = X[0, col], X[1, col], X[2, col]
            block = Z[:, dst:dst + size]
            np.matmul(X0, Z[:, src:src + size].reshape(6, -1), out=block.reshape(6, -1))
            if revolute:  # rotation by -q about z, of the linear and angular parts alike
                c, s = np.cos(x), np.sin(x)
                bx, by = block[0::3], block[1::3]
                rx = c * bx + s * by
                by *= c
                by -= s * bx
                bx[...] = rx
            else:  # translation by q along z
                block[0] += x * block[4]
                block[1] -= x * block[3]
            # a += S qdd + v x (S qd), v += S qd
            v, a = block[:, 0], block[:, 1]
            if revolute:
                a[0] += xd * v[1]
                a[1] -= xd * v[0]
                a[3] += xd * v[4]
                a[4] -= xd * v[3]
                a[5] += xdd
                v[5] += xd
            else:
                a[0] += xd * v[4]
                a[1] -= xd * v[3]
                a[2] += xdd
                v[2] += xd
        # body kinematics: w, wd, the classical origin acceleration minus gravity, |w|^2
        np.take(Z[3:], self.vel, axis=1, out=Kb[0:3], mode='clip')
        np.take(Z[3:], self.vel + 1, axis=1, out=Kb[3:6], mode='clip')
        np.take(Z[:3], self.vel + 1, axis=1, out=Kb[6:9], mode='clip')
        vx, vy, vz = Z[:3, self.vel]
        wx, wy, wz = Kb[0:3]
        Kb[6] += wy * vz - wz * vy
        Kb[7] += wz * vx - wx * vz
        Kb[8] += wx * vy - wy * vx
        Kb[9] = wx * wx + wy * wy + wz * wz
        np.take(Z, self.pair_u, axis=1, out=U, mode='clip')
        C = Z.shape[2]
        for k, Ra, pairs in self.tilted:  # to the joint frame, where the parameters are
            Kb[0:9, k] = _rotate(Ra, Kb[0:9, k].reshape(3, 3, C)).reshape(9, C)
            U[:, pairs] = _rotate(Ra, U[:, pairs].reshape(2, 3, -1, C)).reshape(6, -1, C)
        np.take(Kb, self.pair_body, axis=1, out=K, mode='clip')
        wx, wy, wz, dx, dy, dz, ax, ay, az, ww = K
        lx, ly, lz, ux, uy, uz = U
        Yp[0] = lx * ax + ly * ay + lz * az
        lw = lx * wx + ly * wy + lz * wz
        Yp[1] = ly * dz - lz * dy + wx * lw - lx * ww + ay * uz - az * uy
        Yp[2] = lz * dx - lx * dz + wy * lw - ly * ww + az * ux - ax * uz
        Yp[3] = lx * dy - ly * dx + wz * lw - lz * ww + ax * uy - ay * ux
        cx, cy, cz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
        Yp[4] = ux * dx + cx * wx
        Yp[5] = ux * dy + uy * dx + cx * wy + cy * wx
        Yp[6] = ux * dz + uz * dx + cx * wz + cz * wx
        Yp[7] = uy * dy + cy * wy
        Yp[8] = uy * dz + uz * dy + cy * wz + cz * wy
        Yp[9] = uz * dz + cz * wz
        return Yp
