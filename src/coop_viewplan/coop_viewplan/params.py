"""The `view_planner` node's parameters (declared by the node, validated the same way by
`coop_viewplan.offline`'s `-p` overrides). No rclpy here."""
from __future__ import annotations

from coop_common.frames import FRAME_PARAMS, check_frame_params
from coop_common.params import ParamSpec

from .grid import FreeGray
from .mast import BRAID_HEIGHTS_M, MastKind
from .nbv import NiMeasure
from .placement import PrimarySpace

__all__ = ['PARAMS', 'check_params']

PARAMS = {
    'map_topic': ParamSpec('map/voxels', 'shared map topic (coop_msgs/VoxelMap, latched)',
                           read_only=True),
    'frame_id': ParamSpec('map', "the map's frame when its messages name none; requests must "
                          'be given in the map frame (no TF lookup here), answers are stamped '
                          'with it; after frame_prefix', read_only=True),
    'frame_prefix': FRAME_PARAMS['frame_prefix'],
    'max_grid_cells': ParamSpec(20_000_000, 'largest planning grid (cells) a map may make; a '
                                'bigger one is rejected (a far outlier voxel, a tiny '
                                'resolution)', lo=1000, hi=2_000_000_000),
    'pad_m': ParamSpec(5.0, 'unknown margin added around the known map (m)', lo=0.0, hi=100.0),
    'ceiling_m': ParamSpec(1.0, 'top of the planning grid (z in the map frame, m) unless the map '
                           'reaches higher: no unknown air above it counts as information '
                           '(0: pad upwards too)', lo=0.0, hi=1000.0),
    'fov_deg': ParamSpec(75.0, 'camera horizontal field of view (deg)', lo=5.0, hi=170.0),
    'depth_m': ParamSpec(10.0, 'camera depth of field for mapping (m)', lo=0.5, hi=100.0),
    # 128 x 128 rays cost ~40x the default's per pose (512 x 512: 82 s a decision, blocking
    # the node's one executor)
    'rays_az': ParamSpec(24, 'NI rays across the field of view', lo=2, hi=128),
    'rays_el': ParamSpec(18, 'NI rays up the field of view', lo=2, hi=128),
    'k_rel': ParamSpec(0.15, 'K of Eq. 3-15 relative to the NI of an unknown view per depth',
                       lo=0.0, hi=100.0),
    'n_exp': ParamSpec(1.0, 'n of Eq. 3-15', lo=0.1, hi=4.0),
    'ni_measure': ParamSpec(NiMeasure.HISTOGRAM.value, 'NI binning: gray levels (Eq. 3-13) or '
                            'the App. C predictor-5 residual', choices=tuple(NiMeasure)),
    'free_gray': ParamSpec(FreeGray.EMPTY.value, 'NI gray of known free voxels: 0 (known empty '
                           'space) or their occupancy', choices=tuple(FreeGray)),
    'candidates': ParamSpec(40, 'default candidate positions per decision (x headings)',
                            lo=1, hi=5000),
    'headings': ParamSpec(8, 'candidate headings per position', lo=1, hi=64),
    # rover_sim's mast: c.g. 0.30 m + pan joint 0.40 + tilt 0.04 + camera 0.06 = 0.80 m
    'camera_height_m': ParamSpec(0.8, 'mast camera height above the map origin (m)',
                                 lo=-100.0, hi=100.0),
    'clearance_m': ParamSpec(0.5, 'rover clearance for P (m)', lo=0.0, hi=10.0),
    # A lone occupied voxel in a column is mostly stereo speckle; a real surface gives several
    # or is seen often enough to reach the map's clamp (0.971 in coop_mapping).
    'occupied_voxels': ParamSpec(2, 'occupied voxels of a column (ground clearance up to the '
                                 'camera) that block the rover', lo=1, hi=100),
    # One stereo hit gives P = 0.7 and a later ray through the voxel lowers it to 0.61: far
    # points mis-ranged in front of the surface are carved by nearer views (fig_3_25).
    'occupied_p': ParamSpec(0.7, 'occupancy at which a voxel of a column counts for '
                            'occupied_voxels', lo=0.5, hi=1.0),
    'occupied_clamp': ParamSpec(0.97, 'occupancy at which a single voxel blocks its column',
                                lo=0.5, hi=1.0),
    # The shared map clamps free voxels at P = 0.12 and one free observation gives 0.4
    # (OctoMap's hit/miss/clamp model), so the thesis's P < 0.05 is never met on it;
    # 0.2 = seen free about four times.
    'p_empty': ParamSpec(0.2, 'collision-free threshold on P (Eq. 3-15 constraint (i))',
                         lo=0.0, hi=0.5),
    'max_ranked': ParamSpec(10, 'ranked views returned', lo=1, hi=1000),
    'task_fov_deg': ParamSpec(60.0, 'task camera field of view (deg), Eq. 4-2', lo=5.0,
                              hi=170.0),
    'task_pixels': ParamSpec(640, 'task camera pixels along the axis, Eq. 4-2', lo=1,
                             hi=100000),
    'task_near_m': ParamSpec(0.3, 'task depth of field near limit (m)', lo=0.0, hi=100.0),
    'task_far_m': ParamSpec(5.0, 'task depth of field far limit (m)', lo=0.1, hi=1000.0),
    'task_candidates': ParamSpec(3000, 'cap on the ratings of the placement search', lo=10,
                                 hi=100000),
    # A stereo map of a work site keeps unknown pockets the cameras never saw (under and behind
    # the site, above it): counted as occluders they can hide a target from every nearby
    # camera (coop_insertion's site maps); false treats only mapped obstacles as occluders.
    'task_unknown_occludes': ParamSpec(True, 'task placement: unknown voxels occlude the '
                                       'target and bar a camera station (else only occupied '
                                       'ones; a station in unknown space has P = p_empty / 2)'),
    # The insertion's primary target stands in front of the site, a voxel above its mouth:
    # range noise off the site's edges can occupy a voxel that, grown by the target's radius,
    # holds it ('free': such cells are not occluders of the primary; placement.PrimarySpace).
    'task_primary_space': ParamSpec(PrimarySpace.REFUSE.value, 'task placement: occluder '
                                    'cells holding the primary target refuse the request (the '
                                    "thesis), or are taken as free ('free'; counted in the "
                                    'reply)',
                                    choices=tuple(PrimarySpace)),
    'seed': ParamSpec(0, 'random seed of candidate sampling', lo=0, hi=2 ** 31 - 1),
    # issue #37: a BRAID mast's views are the ones its IK reaches (coop_viewplan.mast); the
    # chosen one's chain state goes to <robot>/mast/braid_command
    'mast': ParamSpec(MastKind.PAN_TILT.value, "the rovers' camera mast: the pan/tilt head "
                      '(views at camera_height_m, pitch 0) or BRAID (the views its IK reaches, '
                      'the chosen state commanded)', choices=tuple(MastKind), read_only=True),
    'braid_stages': ParamSpec(10, "stages of the BRAID mast (as the simulator's)", lo=1,
                              hi=20, read_only=True),
    'braid_heights_m': ParamSpec(list(BRAID_HEIGHTS_M), 'BRAID: the camera heights above the '
                                 'ground (m) wanted at each pitch (the IK keeps the ones it '
                                 'reaches)', read_only=True),
    'braid_pitches_deg': ParamSpec([0.0, 20.0], 'BRAID: the nose-down pitches (deg) wanted at '
                                   'each camera height', read_only=True),
}


def check_params(p: dict) -> str | None:
    """The rule between the view planner's parameters: the reason they do not fit, or None."""
    if not p['task_near_m'] < p['task_far_m']:
        return f"task_near_m ({p['task_near_m']}) must be below task_far_m ({p['task_far_m']})"
    pitches = list(p['braid_pitches_deg'])
    if not pitches or not all(isinstance(v, (int, float)) and -60.0 <= v <= 60.0
                              for v in pitches):
        return f'braid_pitches_deg must be 1 or more pitches within +-60 deg, got {pitches}'
    heights = list(p['braid_heights_m'])
    if not heights or not all(isinstance(v, (int, float)) and 0.0 < v <= 3.0 for v in heights):
        return f'braid_heights_m must be 1 or more heights in (0, 3] m, got {heights}'
    return check_frame_params(p)
