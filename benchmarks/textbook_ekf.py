"""The yardstick of BENCHMARKS.md's speed table: a plain textbook visual-inertial EKF in numpy, the
course formulation, as a student would write it: the convention test, then the filter; no outputs.

    python benchmarks/textbook_ekf.py FILE.npz           # prints the ATE against --gt when given

Model (the course's): the pose world_T_imu = mu exp(delta^) predicted by the body velocities
(mu <- mu exp(tau u^), P_pose <- F P F^T + W with F = Ad(exp(-tau u^)), P_pose,lm <- F P_pose,lm),
stereo observations z = Ks pi(cam_T_imu T^-1 m) of landmarks in the state while their track lives
(added by stereo triangulation with their covariance and cross-covariance, dropped when the track
ends), one joint update a step with every observation (S = H P H^T + sigma^2 I, Joseph form), each
observation gated by its own chi2_4 test (batched). The convention test: the IMU's axes as given or
flipped, the velocity stamped k or k+1, by the median reprojection of points triangulated at k,
carried by dead reckoning to k+3. Fixed noise: 1.5 px, 0.5 m/s and 0.05 rad/s per axis. numpy only
(its BLAS with its default threads) and its own few SE(3) lines (vislam's geometry imports numba, whose
import the yardstick must not pay); no numba, no outputs. BENCHMARKS.md times its whole process
against ``vislam run``'s.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

PIXEL_SIGMA, LINEAR_SIGMA, ANGULAR_SIGMA = 1.5, 0.5, 0.05
CHI2_4 = 18.47  # the 0.999 quantile of chi2 with 4 dof


def hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def exp_se3(xi):
    """exp(xi^) for xi = [rho; phi] (4,4) (Rodrigues and the left Jacobian)."""
    rho, phi = xi[:3], xi[3:]
    t = np.linalg.norm(phi)
    W = hat(phi)
    if t < 1e-9:
        R, J = np.eye(3) + W, np.eye(3) + 0.5 * W
    else:
        R = np.eye(3) + np.sin(t) / t * W + (1 - np.cos(t)) / t**2 * W @ W
        J = np.eye(3) + (1 - np.cos(t)) / t**2 * W + (t - np.sin(t)) / t**3 * W @ W
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, J @ rho
    return T


def adjoint(T):
    A = np.zeros((6, 6))
    R, p = T[:3, :3], T[:3, 3]
    A[:3, :3] = A[3:, 3:] = R
    A[:3, 3:] = hat(p) @ R
    return A


def inverse(T):
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def load(path):
    d = np.load(path, allow_pickle=False)
    K, b = d["K"], float(d["b"])
    if "imu_T_cam" in d:
        cam_T_imu = inverse(d["imu_T_cam"])
    else:
        cam_T_imu = d["cam_T_imu"]
    w = d["angular_velocity"] if "angular_velocity" in d else d["rotational_velocity"]
    return d["time_stamps"].ravel(), d["features"], d["linear_velocity"].T, w.T, K, b, cam_T_imu


def stereo_matrix(K, b):
    fsu, fsv, cu, cv = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array([[fsu, 0, cu, 0], [0, fsv, cv, 0], [fsu, 0, cu, -fsu * b], [0, fsv, cv, 0]])


def triangulate(z, K, b):
    """Camera-frame points (n,3) of stereo pixels z (n,4)."""
    d = z[:, 0] - z[:, 2]
    depth = K[0, 0] * b / d
    return np.column_stack([(z[:, 0] - K[0, 2]) * depth / K[0, 0], (z[:, 1] - K[1, 2]) * depth / K[1, 1], depth])


def project(Ks, q):
    """Stereo pixels (n,4) of camera-frame points q (n,3), and Ks d pi / dq (n,4,4) of the homogeneous point."""
    qh = np.column_stack([q, np.ones(len(q))])
    pix = (Ks @ (qh / q[:, 2:3]).T).T
    J = np.zeros((len(q), 4, 4))
    iz = 1.0 / q[:, 2]
    J[:, 0, 0] = J[:, 1, 1] = J[:, 3, 3] = iz
    J[:, 0, 2] = -q[:, 0] * iz**2
    J[:, 1, 2] = -q[:, 1] * iz**2
    J[:, 3, 2] = -iz**2
    return pix, Ks @ J  # (n,4), (n,4,4)


def convention_test(t, z, v, w, K, b, cam_T_imu, horizon=3):
    """(flip, velocity index) with the smallest median reprojection error."""
    valid = z[0] >= 0
    n = len(t)
    best = None
    Ks = stereo_matrix(K, b)
    for flip in (False, True):
        C = cam_T_imu @ np.diag([1.0, -1.0, -1.0, 1.0]) if flip else cam_T_imu
        for shift in (0, 1):
            errors = []
            for k in range(0, n - horizon - 1, max(1, (n - horizon) // 100)):
                both = valid[:, k] & valid[:, k + horizon] & (z[0, :, k] - z[2, :, k] > 1.0)
                if both.sum() < 5:
                    continue
                T = np.eye(4)
                for j in range(k, k + horizon):
                    dt = t[j + 1] - t[j]
                    T = T @ exp_se3(dt * np.r_[v[j + shift], w[j + shift]])
                s = triangulate(z[:, both, k].T, K, b)
                sh = np.column_stack([s, np.ones(len(s))])
                q = (C @ inverse(T) @ inverse(C) @ sh.T).T[:, :3]
                ok = q[:, 2] > 0.1
                pix, _ = project(Ks, q[ok])
                errors.append(np.linalg.norm(pix - z[:, both, k + horizon].T[ok], axis=1))
            err = float(np.median(np.concatenate(errors))) if errors else np.inf
            if best is None or err < best[0]:
                best = (err, flip, shift)
    return best


def run(path):
    t, z, v, w, K, b, cam_T_imu = load(path)
    err, flip, shift = convention_test(t, z, v, w, K, b, cam_T_imu)
    C = cam_T_imu @ np.diag([1.0, -1.0, -1.0, 1.0]) if flip else cam_T_imu
    C_inv = inverse(C)
    Ks = stereo_matrix(K, b)
    n = len(t)
    valid = z[0] >= 0
    mu = np.eye(4)
    P = np.eye(6) * 1e-12
    ids = np.zeros(0, dtype=int)  # landmark ids in the state, in order
    m = np.zeros((0, 3))
    W = np.diag([LINEAR_SIGMA**2] * 3 + [ANGULAR_SIGMA**2] * 3)
    R1 = PIXEL_SIGMA**2
    poses = [mu.copy()]
    for k in range(n - 1):
        dt = t[k + 1] - t[k]
        u = np.r_[v[k + shift] if k + shift < n else v[k], w[k + shift] if k + shift < n else w[k]]
        step = exp_se3(dt * u)
        mu = mu @ step
        F = adjoint(inverse(step))
        P[:6, :] = F @ P[:6, :]
        P[:, :6] = P[:, :6] @ F.T
        P[:6, :6] += dt**2 * W
        seen = np.flatnonzero(valid[:, k + 1] & (z[0, :, k + 1] - z[2, :, k + 1] > 0.0))
        # tracks that ended leave the state
        keep = np.isin(ids, seen)
        if not keep.all():
            rows = np.r_[np.arange(6), 6 + 3 * np.flatnonzero(keep)[:, None].repeat(3, 1).ravel()
                         + np.tile(np.arange(3), keep.sum())]
            P = P[np.ix_(rows, rows)]
            ids, m = ids[keep], m[keep]
        known = np.isin(seen, ids)
        if known.any():
            obs = seen[known]
            slot = np.searchsorted(ids, obs)
            zk = z[:, obs, k + 1].T
            T_inv = inverse(mu)
            mh = np.column_stack([m[slot], np.ones(len(slot))])
            s = (T_inv @ mh.T).T  # IMU-frame points
            q = (C @ s.T).T[:, :3]
            front = q[:, 2] > 0.1
            pix, J = project(Ks, q)
            r = zk - pix
            D = P.shape[0]
            Hp = np.zeros((len(slot), 4, 6))
            dots = np.zeros((len(slot), 4, 6))
            dots[:, :3, :3] = np.eye(3)
            dots[:, :3, 3:] = -np.array([hat(x) for x in s[:, :3]])
            Hp = -J @ C @ dots  # (n,4,6): right perturbation of the pose
            Hm = J @ C @ T_inv[:, :3]  # (n,4,3)
            # each observation's own chi2 test against its block of S (batched 4 x 4 solves)
            cols = 6 + 3 * slot[:, None] + np.arange(3)  # (n,3)
            P_pm = P[:6][:, cols].transpose(1, 0, 2)  # (n,6,3)
            P_mm = P[cols[:, :, None], cols[:, None, :]]  # (n,3,3)
            Si = (Hp @ P[:6, :6] @ Hp.transpose(0, 2, 1) + Hp @ P_pm @ Hm.transpose(0, 2, 1)
                  + Hm @ P_pm.transpose(0, 2, 1) @ Hp.transpose(0, 2, 1) + Hm @ P_mm @ Hm.transpose(0, 2, 1)
                  + R1 * np.eye(4))
            d2 = np.einsum("ni,ni->n", r, np.linalg.solve(Si, r[:, :, None])[:, :, 0])
            use = np.flatnonzero(front & (d2 <= CHI2_4))
            if use.size:
                H = np.zeros((4 * use.size, D))
                rows = np.arange(4 * use.size).reshape(-1, 4)
                H[rows[:, :, None], np.arange(6)] = Hp[use]
                H[rows[:, :, None], cols[use][:, None, :]] = Hm[use]
                PHt = P @ H.T
                S = H @ PHt + R1 * np.eye(H.shape[0])
                Kg = np.linalg.solve(S, PHt.T).T
                dx = Kg @ r[use].ravel()
                mu = mu @ exp_se3(dx[:6])
                m = m + dx[6:].reshape(-1, 3)
                IKH = np.eye(D) - Kg @ H
                P = IKH @ P @ IKH.T + R1 * Kg @ Kg.T
                P = 0.5 * (P + P.T)
        new = seen[~known]
        if new.size:
            zk = z[:, new, k + 1].T
            s_c = triangulate(zk, K, b)
            sh = np.column_stack([s_c, np.ones(len(s_c))])
            s_i = (C_inv @ sh.T).T
            mw = (mu @ s_i.T).T[:, :3]
            ok = (s_c[:, 2] > 0.1) & (s_c[:, 2] < 200.0)
            new, mw, s_i, zk = new[ok], mw[ok], s_i[ok], zk[ok]
            if new.size:
                D = P.shape[0]
                d = zk[:, 0] - zk[:, 2]
                G = np.zeros((3 * new.size, 6))  # d m / d pose of every new landmark (m = mu s)
                noise = np.zeros((3 * new.size, 3 * new.size))  # ... and their pixels' part, landmark by landmark
                for j in range(new.size):
                    G[3 * j:3 * j + 3] = mu[:3, :3] @ np.hstack([np.eye(3), -hat(s_i[j, :3])])
                    depth = K[0, 0] * b / d[j]
                    dd = np.zeros((3, 4))  # d s_c / d z
                    dd[2, 0], dd[2, 2] = -depth / d[j], depth / d[j]
                    dd[0, 0] = depth / K[0, 0] + (zk[j, 0] - K[0, 2]) / K[0, 0] * dd[2, 0]
                    dd[0, 2] = (zk[j, 0] - K[0, 2]) / K[0, 0] * dd[2, 2]
                    dd[1, 1] = depth / K[1, 1]
                    dd[1, 0], dd[1, 2] = (zk[j, 1] - K[1, 2]) / K[1, 1] * dd[2, 0], (zk[j, 1] - K[1, 2]) / K[1, 1] * dd[2, 2]
                    G_z = mu[:3, :3] @ C_inv[:3, :3] @ dd
                    noise[3 * j:3 * j + 3, 3 * j:3 * j + 3] = R1 * G_z @ G_z.T
                Pn = np.zeros((D + 3 * new.size, D + 3 * new.size))
                Pn[:D, :D] = P
                Pn[D:, :D] = G @ P[:6, :D]
                Pn[:D, D:] = Pn[D:, :D].T
                Pn[D:, D:] = G @ P[:6, :6] @ G.T + noise
                P = Pn
                order = np.argsort(np.r_[ids, new], kind="stable")
                ids = np.r_[ids, new][order]
                m = np.vstack([m, mw])[order]
                rows = np.r_[np.arange(6), (6 + 3 * order[:, None] + np.arange(3)).ravel()]
                P = P[np.ix_(rows, rows)]
        poses.append(mu.copy())
    return t, np.array(poses), (err, flip, shift)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file")
    parser.add_argument("--gt", help="TUM ground truth: print the ATE (SE(3)-aligned, evo)")
    args = parser.parse_args(argv)
    t, poses, conventions = run(args.file)
    print(f"textbook EKF: {len(t)} steps; conventions (median px, flip, velocity shift) {conventions}")
    if args.gt:
        from vislam.backend.data.tum import read_tum
        from vislam.backend.evaluation.metrics import trajectory_errors

        gt_t, gt = read_tum(args.gt)
        print(f"ATE {trajectory_errors(t, poses, gt_t, gt).ate_rmse:.3f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
