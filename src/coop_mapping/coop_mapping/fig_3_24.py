"""Fig. 3-24 analogue: accumulated r.m.s. camera translation error per scan step, with and
without fiducial-based camera motion correction (Sujan 2002, §3.2.5, §3.3.2).

A stereo camera (the rover's: 41.2 deg FOV, 38 mm baseline) steps sideways past a textured
scene at an average distance of 1100 mm and of 350 mm (the thesis's two cases; the scene is
scaled with the distance). Every step's true motion is the commanded one composed with a random
error (mast vibration / base compliance: translation and rotation, fixed per-step sigmas, the same
at both distances), so the dead-reckoned pose (commanded chain, what `stereo/pose` carries)
drifts like a random walk. The corrected pose is the commanded step from the previous corrected
pose, fused by covariance (Kalman update, the per-step sigmas known) with the pose measured from
the fiducials; with --no-fusion it is the fiducial measurement alone. Fiducials are chosen in the
images by the fiducial evaluation function (Eq. 3-21/3-22, with the map certainty term from a
VoxelMap of the first scan), tracked by Lucas-Kanade, ranged by StereoSGBM, g01 by least squares
(Eq. 3-16..3-18, or the rigid / reprojection alternatives), averaged over the frames taken at
each step (Eq. 3-19), and the fiducials' positions refined by the EKF of Eq. 3-20; a fiducial is
replaced only when the tracker loses it or the fit rejects it. The SGBM disparity search range
is set, like a rig's working range, from the nearest depth in the first view plus a 20 % margin
(search_range). The true pose and depth are used only to render the images, to set that range,
and to score the result.

    fig_3_24 --json out/fig_3_24.json --plots out/fig_3_24.png
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from coop_common.cli import enum_choices, figure_path, number, output_path
from coop_common.files import save_figure, write_json
from coop_common.params import choice

from .errors import MappingError
from .fiducial_odometry import FiducialOdometry, OdometryConfig, PoseMethod
from .render import Box, TexturedScene, look_at
from .stereo import (
    FULL_WIDTH_DEFAULT,
    SUBPIXEL_DEFAULT,
    StereoCamera,
    Subpixel,
    compute_disparity,
)


@dataclass(frozen=True)
class TrialConfig:
    """One Fig. 3-24 trial's settings: the scene's distance, the steps and their errors."""

    distance: float = 1.1          # m, average distance of the scene from the camera
    steps: int = 20
    step_m: float = 0.04           # commanded sideways motion per step at 1.1 m (scaled)
    sigma_t_m: float = 0.002       # per-step translation error, per axis
    sigma_rot_deg: float = 0.2     # per-step rotation error, per axis
    frames_per_step: int = 2       # stereo frames averaged by Eq. 3-19 at each step
    image_noise: float = 2.0       # grey levels
    width: int = 320
    height: int = 240
    n_fiducials: int = 40
    num_disparities: int | None = None   # SGBM search range; None: from the camera and the
                                         # nearest depth in the first view (search_range)
    method: PoseMethod = PoseMethod.LINEAR   # g01 (fiducial_odometry.PoseMethod)
                                   # (reprojection of the mapped fiducials, no range in the fit)
    fuse_prediction: bool = True   # Kalman-fuse the commanded motion (known per-step sigmas)
                                   # with the fiducial measurement; False: fiducials only
    subpixel: Subpixel = SUBPIXEL_DEFAULT  # sub-pixel disparity (stereo.compute_disparity)
    full_width: bool = FULL_WIDTH_DEFAULT  # range the left num_disparities columns too (same)

    def __post_init__(self) -> None:
        for name, kind in (('method', PoseMethod), ('subpixel', Subpixel)):
            object.__setattr__(self, name, choice(kind, getattr(self, name), name,
                                                  error=ConfigError))

    @classmethod
    def thesis(cls, **changes: Any) -> TrialConfig:
        """The thesis's motion estimate from the fiducials: g01 by Eq. 3-18 as printed
        ('linear', the default). `changes`: the scene and the sensor."""
        return cls(**{'method': PoseMethod.LINEAR, **changes})

    @classmethod
    def best_measured(cls, **changes: Any) -> TrialConfig:
        """The fit beyond the thesis that measured best on Fig. 3-24 (coop_mapping README): the
        covariance-weighted rigid fit, fused with the commanded motion (final error reduction
        60 % / 78 % at 1100 / 350 mm, where the printed Eq. 3-18 gave -9 % / 65 %)."""
        return cls(**{'method': PoseMethod.RIGID, 'fuse_prediction': True, **changes})


def _scene_boxes(s: float) -> list[Box]:
    return [Box((0.9 * s, 0.0, -0.05 * s), (1.2 * s, 2.0 * s, 0.05 * s)),      # ground
            Box((1.55 * s, 0.0, 0.6 * s), (0.05 * s, 2.0 * s, 0.6 * s)),       # back wall
            Box((1.0 * s, -0.35 * s, 0.25 * s), (0.1 * s, 0.12 * s, 0.25 * s)),
            Box((1.15 * s, 0.1 * s, 0.4 * s), (0.12 * s, 0.1 * s, 0.15 * s)),
            Box((0.95 * s, 0.45 * s, 0.35 * s), (0.08 * s, 0.15 * s, 0.2 * s)),
            Box((1.2 * s, -0.8 * s, 0.3 * s), (0.1 * s, 0.1 * s, 0.3 * s)),
            Box((1.05 * s, 0.85 * s, 0.2 * s), (0.1 * s, 0.1 * s, 0.2 * s))]


def _se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _small_rot(w: np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))
    return R


def search_range(cam: StereoCamera, z_near: float, margin: float = 0.2) -> int:
    """SGBM disparity search range covering every depth >= z_near / (1 + margin): (1 + margin)
    f b / z_near pixels, rounded up to the multiple of 16 SGBM needs. A fixed range does not
    follow the camera and the scene: at 640x480 the 350 mm scene's ground is at 53-117 px of
    disparity, and with 64 SGBM returned wrong matches (median error 19 px) over most of the
    image. The margin is for the trajectory: the camera moves and shakes after the first view,
    and the nearest true disparity met is up to 11 % above the first view's at 350 mm (320x240:
    58 -> 64.3 px; with a 10 % margin the range came out 64 px and missed it)."""
    if margin < 0:
        raise ValueError('margin must be >= 0')
    return int(16 * np.ceil((1.0 + margin) * cam.fx * cam.baseline / z_near / 16))


class ConfigError(MappingError, ValueError):
    """A trial setting the rig cannot run (found before any trial)."""


def _rig(cfg: TrialConfig) -> tuple[StereoCamera, float, np.ndarray]:
    """The camera, the scene scale and the first camera pose of a trial."""
    s = cfg.distance / 1.1
    cam = StereoCamera.from_fov(cfg.width, cfg.height, np.radians(41.2), 0.038)
    eye = np.array([-0.35 * s, -0.4 * s, 0.45 * s])
    return cam, s, _se3(look_at(eye, eye + np.array([1.0, 0.0, -0.25])), eye)


def _scene(cam: StereoCamera, s: float, seed: int) -> TexturedScene:
    # the scene, the renderer's clip planes and the camera path all scale with the distance
    return TexturedScene(cam, boxes=_scene_boxes(s), seed=seed, tile_m=0.8 * s, near=0.05 * s,
                         far=30.0 * max(1.0, s))


def _working_range(cfg: TrialConfig, cam: StereoCamera, scene: TexturedScene,
                   T0: np.ndarray) -> int:
    """The rig's SGBM search range for its working range (the nearest depth of the first
    view); ConfigError when the images are not wider than it (SGBM cannot run on them)."""
    depth = scene.render(T0[:3, :3], T0[:3, 3])[2]
    if not np.isfinite(depth).any():
        raise ConfigError(f'scene at {cfg.distance:g} m: nothing in the first view')
    nd = cfg.num_disparities or search_range(cam, float(np.nanmin(depth)))
    if cfg.width <= nd:
        raise ConfigError(f'scene at {cfg.distance:g} m: a disparity range of {nd} px, not less '
                         f'than the image width {cfg.width}; a wider image or a farther scene')
    return nd


def check_config(cfg: TrialConfig) -> int:
    """The search range a trial of `cfg` will use, or ConfigError before any trial runs (the
    first view alone is rendered; the scene's geometry does not depend on the seed)."""
    cam, s, T0 = _rig(cfg)
    with _scene(cam, s, 0) as scene:
        return _working_range(cfg, cam, scene, T0)


def run_trial(cfg: TrialConfig, seed: int) -> dict:
    """One trajectory: translation error per step of the dead-reckoned and corrected poses."""
    rng = np.random.default_rng(seed)
    cam, s, T0 = _rig(cfg)
    step_world = np.array([0.0, cfg.step_m * s, 0.0])
    T_cmd = T0.copy()
    T_true = T0.copy()
    err_dr, err_fc = [0.0], [0.0]
    with _scene(cam, s, seed) as scene:
        # the rig is set up for its working range: the nearest depth in the first view
        nd = _working_range(cfg, cam, scene, T0)
        d_max = [0.0]                    # largest true disparity met, to check the range

        def frames(T: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
            out = []
            for _ in range(cfg.frames_per_step):
                left, right, depth = scene.render(T[:3, :3], T[:3, 3],
                                                  noise_sigma=cfg.image_noise, rng=rng)
                d_max[0] = max(d_max[0], cam.fx * cam.baseline / float(np.nanmin(depth)))
                out.append((left, compute_disparity(left, right, num_disparities=nd,
                                                    subpixel=cfg.subpixel,
                                                    full_width=cfg.full_width)))
            return out

        sig = ({'sigma_t_m': cfg.sigma_t_m, 'sigma_rot_rad': np.radians(cfg.sigma_rot_deg)}
               if cfg.fuse_prediction else {})
        fo = FiducialOdometry(cam, OdometryConfig(n_fiducials=cfg.n_fiducials,
                                                  method=cfg.method, scene_distance=cfg.distance,
                                                  spacing_px=cfg.width / 16, **sig), T0)
        f0 = frames(T_true)
        fo.first(*f0[0])
        for _ in range(cfg.steps):
            T_cmd_next = T_cmd.copy()
            T_cmd_next[:3, 3] += step_world
            delta = np.linalg.inv(T_cmd) @ T_cmd_next           # commanded, camera frame
            E = _se3(_small_rot(rng.normal(0, np.radians(cfg.sigma_rot_deg), 3)),
                     rng.normal(0, cfg.sigma_t_m, 3))
            T_true = T_true @ delta @ E
            T_cmd = T_cmd_next
            T_est = fo.step(frames(T_true), delta)
            err_dr.append(float(np.linalg.norm(T_cmd[:3, 3] - T_true[:3, 3])))
            err_fc.append(float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])))
    return {'dead_reckoned': err_dr, 'corrected': err_fc, 'fallbacks': fo.fallbacks,
            'num_disparities': nd, 'max_true_disparity_px': d_max[0], 'kept': fo.kept}


def run(distances: list[float], trials: int, steps: int, seed: int = 0,
        width: int = 320, height: int = 240,
        methods: tuple[PoseMethod | str, ...] = (PoseMethod.LINEAR,),
        fuse_prediction: bool = True, subpixel: Subpixel | str = SUBPIXEL_DEFAULT,
        full_width: bool = FULL_WIDTH_DEFAULT) -> dict:
    """Every method at every distance, `trials` runs each; an unknown method or sub-pixel
    mode, or a distance the rig cannot run, is a ConfigError before the first trial."""
    poses = tuple(choice(PoseMethod, m, 'method', error=ConfigError) for m in methods)
    subpixel = choice(Subpixel, subpixel, 'subpixel', error=ConfigError)
    out: dict[str, Any] = {
        'distances_m': distances, 'trials': trials, 'steps': steps, 'seed': seed,
        'width': width, 'height': height, 'fuse_prediction': fuse_prediction,
        'subpixel': subpixel, 'full_width': full_width, 'results': {}}

    def config(D: float, method: PoseMethod) -> TrialConfig:
        return TrialConfig(distance=D, steps=steps, width=width, height=height, method=method,
                           fuse_prediction=fuse_prediction, subpixel=subpixel,
                           full_width=full_width)

    for D in distances:             # every distance checked before the first trial
        check_config(config(D, poses[0]))
    for method in poses:
        for D in distances:
            cfg = config(D, method)
            # same seeds for every method: the same true trajectories and images
            runs = [run_trial(cfg, seed + 1000 * i) for i in range(trials)]
            dr = np.array([r['dead_reckoned'] for r in runs])
            fc = np.array([r['corrected'] for r in runs])
            rms_dr = np.sqrt(np.mean(dr ** 2, 0))
            rms_fc = np.sqrt(np.mean(fc ** 2, 0))
            out['results'].setdefault(method, {})[f'{D:g}'] = {
                'config': cfg.__dict__,
                'rms_error_dead_reckoned_m': rms_dr.tolist(),
                'rms_error_corrected_m': rms_fc.tolist(),
                'final_reduction': float(1 - rms_fc[-1] / rms_dr[-1]),
                'mean_reduction': float(1 - rms_fc[1:].mean() / rms_dr[1:].mean()),
                'fallback_steps': int(sum(r['fallbacks'] for r in runs)),
                'num_disparities': [r['num_disparities'] for r in runs],
                'max_true_disparity_px': [r['max_true_disparity_px'] for r in runs],
                # fiducials carried over from the previous step (of n_fiducials), mean per step
                'fiducials_kept_per_step': float(np.mean([r['kept'] for r in runs])),
            }
    return out


def format_table(out: dict) -> str:
    """The table main prints, from the JSON result of `run` (docs/results pages are made with
    it): the RMS errors at every quarter of the trajectory, then one summary line per method and
    distance."""
    first = next(iter(next(iter(out['results'].values())).values()))['config']
    lines = [f'images {out["width"]}x{out["height"]}, {out["trials"]} trials, {out["steps"]} '
             f'steps; per-step motion error sigma {first["sigma_t_m"] * 1e3:g} mm, '
             f'{first["sigma_rot_deg"]:g} deg per axis; corrected pose: '
             + ('commanded motion and fiducial measurement fused by covariance'
                if out['fuse_prediction'] else 'fiducial measurement alone')
             + f'; sub-pixel disparity {out["subpixel"]}'
             + (', full width' if out['full_width']
                else ', without the left search-range columns'),
             f'{"method":>6} {"dist m":>6} {"step":>4} {"RMS dead-reckoned mm":>21} '
             f'{"RMS corrected mm":>17}']
    for method, per in out['results'].items():
        for D, r in per.items():
            for k in range(0, out['steps'] + 1, max(1, out['steps'] // 4)):
                lines.append(f'{method:>6} {D:>6} {k:4d} '
                             f'{1e3 * r["rms_error_dead_reckoned_m"][k]:21.2f} '
                             f'{1e3 * r["rms_error_corrected_m"][k]:17.2f}')
    for method, per in out['results'].items():
        for D, r in per.items():
            lines.append(f'{method:>6} distance {D} m: final error reduction '
                         f'{100 * r["final_reduction"]:.1f}%, mean over steps '
                         f'{100 * r["mean_reduction"]:.1f}%, fallback steps '
                         f'{r["fallback_steps"]}, fiducials kept/step '
                         f'{r["fiducials_kept_per_step"]:.1f} of {r["config"]["n_fiducials"]}, '
                         f'disparity range {max(r["num_disparities"])} '
                         f'(true max {max(r["max_true_disparity_px"]):.1f}) px')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_mapping.fig_3_24`: the camera translation error with and without fiducials
    (Fig. 3-24)."""
    ap = argparse.ArgumentParser(description='Fig. 3-24: camera translation error with and '
                                 'without fiducial correction')
    ap.add_argument('--json', type=output_path)
    ap.add_argument('--plots', type=figure_path, help='figure of the RMS error per step (.png, '
                    '.pdf or .svg)')
    ap.add_argument('--trials', type=number(int, lo=1, hi=1000), default=3)
    ap.add_argument('--steps', type=number(int, lo=1, hi=10_000), default=20)
    ap.add_argument('--seed', type=number(int, lo=0, hi=2 ** 32 - 1), default=0)
    ap.add_argument('--distances', type=number(float, lo=0.0, lo_open=True, hi=100.0),
                    nargs='+', default=[1.1, 0.35],
                    help='average distances of the scene (m); the images must be wider than '
                    'the disparity range the nearest one needs')
    ap.add_argument('--methods', nargs='+', choices=enum_choices(PoseMethod),
                    default=enum_choices(PoseMethod),
                    help='g01 by Eq. 3-18 as printed (12 independent entries), the same with R '
                    'projected onto SO(3) and X re-solved (linear_so3), the covariance-weighted '
                    'rigid fit, or reprojection of the mapped fiducials (pnp)')
    ap.add_argument('--no-fusion', action='store_true',
                    help='corrected pose from the fiducial measurement alone, the commanded '
                    'motion only as its starting point (no Kalman update with the prediction)')
    ap.add_argument('--width', type=number(int, lo=32, hi=4096), default=320)
    ap.add_argument('--height', type=number(int, lo=32, hi=4096), default=240)
    ap.add_argument('--subpixel', choices=enum_choices(Subpixel), default=SUBPIXEL_DEFAULT.value,
                    help="sub-pixel disparity (stereo.compute_disparity): SGBM's own, "
                    'equalised, or the mean over 2 / 4 sub-pixel shifts of the right image')
    ap.add_argument('--full-width', action=argparse.BooleanOptionalAction,
                    default=FULL_WIDTH_DEFAULT,
                    help='range the left num_disparities columns too (stereo.compute_disparity)')
    args = ap.parse_args(argv)
    try:        # run() checks every distance's first view before its first trial
        out = run(args.distances, args.trials, args.steps, args.seed, args.width, args.height,
                  tuple(args.methods), fuse_prediction=not args.no_fusion,
                  subpixel=args.subpixel, full_width=args.full_width)
    except ConfigError as exc:
        ap.error(str(exc))
    print(format_table(out))
    if args.json:
        write_json(args.json, out, indent=2)
    if args.plots:
        import matplotlib  # noqa: PLC0415 - heavy, only when plots are asked for
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt  # noqa: PLC0415
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for method, per in out['results'].items():
            for D, r in per.items():
                k = np.arange(len(r['rms_error_corrected_m']))
                if method == next(iter(out['results'])):
                    ax.plot(k, 1e3 * np.array(r['rms_error_dead_reckoned_m']),
                            'k--' if float(D) > 0.5 else 'k:',
                            label=f'{float(D) * 1e3:.0f} mm, uncorrected')
                ax.plot(k, 1e3 * np.array(r['rms_error_corrected_m']), '-',
                        label=f'{float(D) * 1e3:.0f} mm, fiducials ({method})')
        ax.set_xlabel('scan step')
        ax.set_ylabel('accumulated r.m.s. translation error (mm)')
        ax.legend()
        ax.grid(alpha=0.3)
        save_figure(fig, args.plots, dpi=120)
    return 0


if __name__ == '__main__':
    sys.exit(main())
