"""Node `view_planner`: next-best-view (Eq. 3-15) and task-directed placement (Eq. 4-1) services
on the shared map.

Subscribes `map/voxels` (coop_msgs/VoxelMap, latched). Services `viewplan/next_best_view`
(coop_msgs/srv/NextBestView) and `viewplan/task_view` (coop_msgs/srv/TaskView). Bad requests
(unknown strategy, empty map, no free candidate, target inside an obstacle) answer
success=false with the reason. With `mast:=braid` the next best view is one the BRAID mast's IK
reaches, and its chain state is published on `<robot>/mast/braid_command`
(std_msgs/UInt8MultiArray, the request's robot; the turntable's heading offset in the reply's
message: pan = the view's yaw - the rover's heading - that offset).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from rclpy.exceptions import InvalidTopicNameException
from rclpy.node import Node
from std_msgs.msg import UInt8MultiArray

from coop_common.node_util import BadInputCounter, declare_parameters, run_node
from coop_common.params import choice
from coop_common.qos import LATCHED_QOS
from coop_msgs.msg import ViewRating, VoxelMap
from coop_msgs.srv import NextBestView, TaskView

from .frames import camera_pose, look_at_quaternion, optical_quaternion
from .grid import EmptyMapError, MapError, OccupancyGrid, planning_grid
from .mast import MastKind
from .nbv import CameraState, NextBestViewPlanner, PlanningError, StrategyName
from .offline import nbv_config, node_braid_views
from .params import PARAMS, check_params
from .placement import (
    CameraModel,
    Choose,
    PlacementError,
    Target,
    TaskPlacer,
    mast_stations,
)

#: TaskView.Request.choose -> the placer's Choose
CHOOSE = {TaskView.Request.CHOOSE_BEST: Choose.BEST,
          TaskView.Request.CHOOSE_RANDOM: Choose.RANDOM}


class ViewPlannerNode(Node):
    """The view planner: the team's map in; next best views and task camera poses served."""

    def __init__(self, **kwargs) -> None:
        super().__init__('view_planner', **kwargs)
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params,
                                    check_all=check_params)
        self.bad = BadInputCounter(self)
        self.rng = np.random.default_rng(int(self.p['seed']))
        self.grid: OccupancyGrid | None = None
        # why grid is None: no map yet, an empty one, or every one so far refused
        self.map_state = 'empty map: nothing received on the map topic yet'
        self.default_frame = self.p['frame_prefix'] + self.p['frame_id']
        self.map_frame = self.default_frame
        self.sequence = -1
        self.cameras: dict[str, CameraState] = {}
        self.expected: dict[str, tuple[int, np.ndarray]] = {}
        self.mast = MastKind(self.p['mast'])
        self._braid_pubs: dict[str, object] = {}     # per robot: its mast/braid_command
        self._build()
        self.create_subscription(VoxelMap, self.p['map_topic'], self._on_map, LATCHED_QOS)
        self.create_service(NextBestView, 'viewplan/next_best_view', self._on_nbv)
        self.create_service(TaskView, 'viewplan/task_view', self._on_task)
        self.get_logger().info('view_planner ready')

    def _on_params(self, changed: dict) -> None:
        self.p.update(changed)
        if 'seed' in changed:
            self.rng = np.random.default_rng(int(self.p['seed']))
        self._build()

    def _build(self) -> None:
        p = self.p
        self.planner = NextBestViewPlanner(nbv_config(p))
        self.placer = TaskPlacer(CameraModel(fov_deg=p['task_fov_deg'], pixels=p['task_pixels'],
                                             near_m=p['task_near_m'], far_m=p['task_far_m']),
                                 clearance_m=p['clearance_m'], p_empty=p['p_empty'],
                                 max_candidates=p['task_candidates'], cache_fields=16,
                                 unknown_occludes=p['task_unknown_occludes'],
                                 primary_space=p['task_primary_space'])
        self._stations = (None, None)       # (grid, its mast stations)

    def _on_map(self, msg: VoxelMap) -> None:
        try:
            grid = planning_grid(msg.voxels.keys, msg.voxels.occupancy, msg.resolution_m,
                                 pad_m=self.p['pad_m'], ceiling_m=self.p['ceiling_m'],
                                 camera_height_m=self.p['camera_height_m'],
                                 max_cells=self.p['max_grid_cells'])
        except EmptyMapError:
            self.grid = None
            self.map_state = 'empty map: the last map received has no voxels'
            self.sequence = int(msg.sequence)
            return
        except MapError as exc:
            self._refuse('bad map', str(exc))
            return
        old = self.grid
        if old is not None and old.resolution == grid.resolution:
            # the cameras' scan positions are grid indices: follow the grid's origin
            shift = np.rint((old.origin - grid.origin)[:2] / grid.resolution).astype(np.int64)
            for cam in self.cameras.values():
                cam.visited = [np.asarray(v) + shift for v in cam.visited]
        elif old is not None:
            self.cameras.clear()
        self.grid = grid
        self.map_frame = msg.header.frame_id or self.default_frame
        self.sequence = int(msg.sequence)
        self.get_logger().debug(f'map {self.sequence}: {len(msg.voxels.occupancy)} voxels')

    def _refuse(self, reason: str, detail: str) -> None:
        """Count a map that cannot be planned on; the last good one (if any) stays."""
        self.bad.reject(reason, detail)
        if self.grid is None:
            self.map_state = ('no map to plan on: the last map received was refused '
                              f'({reason}: {detail})')

    def _rating_msg(self, frame: str, pos: np.ndarray, quat: np.ndarray) -> ViewRating:
        r = ViewRating()
        r.pose.header.frame_id = frame
        r.pose.header.stamp = self.get_clock().now().to_msg()
        r.pose.pose.position.x, r.pose.pose.position.y, r.pose.pose.position.z = (
            float(v) for v in pos)
        (r.pose.pose.orientation.x, r.pose.pose.orientation.y, r.pose.pose.orientation.z,
         r.pose.pose.orientation.w) = (float(v) for v in quat)
        for k in ('new_information_bits', 'distance', 'depth_of_field', 'resolution',
                  'field_visibility', 'angular_visibility'):
            setattr(r, k, math.nan)
        return r

    def _on_nbv(self, req: NextBestView.Request, resp: NextBestView.Response):
        resp.success = False
        try:
            strategy = choice(StrategyName, req.strategy, 'strategy')
        except ValueError as exc:
            resp.message = str(exc)
            return resp
        if self.grid is None:
            resp.message = self.map_state
            return resp
        g = self.grid
        if not self._in_map_frame(req.current_pose.header.frame_id, resp):
            return resp
        pos = req.current_pose.pose.position
        q = req.current_pose.pose.orientation
        try:
            position, yaw, pitch = camera_pose([pos.x, pos.y, pos.z], [q.x, q.y, q.z, q.w])
        except ValueError as exc:
            resp.message = str(exc)
            return resp
        robot = req.robot or 'default'
        cam = self.cameras.setdefault(robot, CameraState(position))
        cam.position, cam.yaw, cam.pitch = position, yaw, pitch
        cam.visited.append(g.to_index(position)[:2])
        claimed = np.zeros(g.shape, bool)
        for other, (seq, mask) in self.expected.items():
            if other != robot and seq == self.sequence and mask.shape == g.shape:
                claimed |= mask
        planner = self.planner
        if req.max_candidates:
            n = min(int(req.max_candidates), PARAMS['candidates'].hi)
            planner = NextBestViewPlanner(replace(planner.config, n_positions=n))
        try:
            d = planner.plan(g, cam, strategy=strategy, rng=self.rng, claimed=claimed,
                             free_footprint=True,
                             teammates=[(p.x, p.y) for p in req.teammates])
        except (MapError, PlanningError, ValueError) as exc:
            resp.message = str(exc)
            return resp
        self.expected[robot] = (self.sequence, planner.expected_cells(g, d))
        frame = self.map_frame
        order = d.ranked()[: int(self.p['max_ranked'])]
        c = d.candidates
        for i in order:
            r = self._rating_msg(frame, c.positions[i], optical_quaternion(c.yaw[i], c.pitch[i]))
            r.rating = float(d.rating[i])
            r.new_information_bits = float(d.scores.ni[i])
            r.distance = float(c.distance[i])
            r.collision_probability = float(c.collision_p[i])
            resp.ranked.append(r)
        best = self._rating_msg(frame, d.position, optical_quaternion(d.yaw, d.pitch))
        best.rating = float(d.rating[d.index])
        best.new_information_bits = float(d.scores.ni[d.index])
        best.distance = float(c.distance[d.index])
        best.collision_probability = float(c.collision_p[d.index])
        resp.best = best
        resp.success = True
        resp.message = (f'{strategy}: {len(c)} candidates, NI {best.new_information_bits:.3f}'
                        f' bits, d {best.distance:.2f} m')
        if self.mast is MastKind.BRAID and d.view >= 0:
            resp.message += self._command_braid(req.robot, d.view)
        return resp

    def _command_braid(self, robot: str, view: int) -> str:
        """Publish the chosen view's chain state to the robot's mast; what to add to the
        reply's message."""
        bv = node_braid_views(self.p)
        states = [int(v) for v in bv.states[view]]
        head = math.degrees(bv.views[view].heading_rad)
        note = f'; BRAID state {states}, turntable offset {head:.2f} deg'
        if not robot:
            return note + ' (no robot named: not commanded)'
        pub = self._braid_pubs.get(robot)
        if pub is None:
            try:
                # latched (as the simulator subscribes): the publisher is made at the first
                # answer for this robot, before discovery has matched it with the mast's
                pub = self.create_publisher(UInt8MultiArray, f'{robot}/mast/braid_command',
                                            LATCHED_QOS)
            except InvalidTopicNameException as exc:
                self.bad.reject('robot name', f'{robot!r}: {exc}')
                return note + f' (robot {robot!r} is no topic name: not commanded)'
            self._braid_pubs[robot] = pub
        pub.publish(UInt8MultiArray(data=states))
        return note + f' (commanded on {robot}/mast/braid_command)'

    @staticmethod
    def _target(msg, *, primary: bool) -> Target:
        """A TaskTarget as a Target: weight <= 0 means 1, negative radius / sigma 0 (the
        message's defaults); non-finite numbers are a PlacementError."""
        pos = np.array([msg.position.x, msg.position.y, msg.position.z])
        nrm = np.array([msg.normal.x, msg.normal.y, msg.normal.z])
        def at_least_0(v: float) -> float:      # nan stays nan: Target rejects it
            return v if math.isnan(v) else max(0.0, float(v))
        weight = 1.0 if primary or msg.weight <= 0 else float(msg.weight)
        return Target(pos, nrm, radius=at_least_0(msg.radius_m),
                      sigma=0.0 if primary else at_least_0(msg.position_sigma_m),
                      weight=weight)


    def _in_map_frame(self, frame: str, resp) -> bool:
        """A request's frame must be the map's (or empty): no TF lookup here."""
        if frame and frame != self.map_frame:
            resp.message = (f'request in frame {frame!r}; the map and the answers are in '
                            f'{self.map_frame!r} (transform before asking)')
            return False
        return True

    def _task_stations(self, g: OccupancyGrid):
        """Where the mast camera may stand: over navigable ground, its voxel seen free; with
        task_unknown_occludes false (unknown space is taken as free for the task), also where
        its voxel is unknown, at P = p_empty / 2 (between a voxel seen free and the free
        threshold): a stereo map seldom sees the layer of the camera itself."""
        trav = self.planner.traversability(g)
        ok, p = trav.candidate, trav.collision_p
        if not self.p['task_unknown_occludes']:
            kc = int(g.to_index(np.r_[g.origin[:2], self.p['camera_height_m']])[2])
            unknown = (~g.known[:, :, kc] if 0 <= kc < g.shape[2]
                       else np.ones(g.shape[:2], bool))
            extra = trav.navigable & unknown & ~ok
            ok = ok | extra
            p = np.where(extra, 0.5 * self.p['p_empty'], p)
        return mast_stations(g, ok, p, self.p['camera_height_m'])

    def _on_task(self, req: TaskView.Request, resp: TaskView.Response):
        resp.success = False
        if self.grid is None:
            resp.message = self.map_state
            return resp
        for t in [req.primary, *req.secondary]:
            if not self._in_map_frame(t.header.frame_id, resp):
                return resp
        g = self.grid
        try:
            prim = self._target(req.primary, primary=True)
            sec = [self._target(s, primary=False) for s in req.secondary]
            stations = None
            if g.ndim == 3:     # the camera on the rover's mast, where the rover may stand
                if self._stations[0] is not g:
                    self._stations = (g, self._task_stations(g))
                stations = self._stations[1]
            if not (math.isfinite(req.near_m) and math.isfinite(req.far_m)):
                raise PlacementError('near_m and far_m must be finite')
            if not 0.0 <= req.max_incidence_deg <= 90.0:      # nan fails too
                raise PlacementError('max_incidence_deg must be in [0, 90]')
            if req.choose not in CHOOSE:
                raise PlacementError(f'choose must be one of {sorted(CHOOSE)}, not '
                                     f'{req.choose}')
            choose = CHOOSE[req.choose]
            placer = self.placer.narrowed(req.near_m, req.far_m,
                                          max_incidence_deg=req.max_incidence_deg)
            # a random draw is the request's seed's: the same request, the same pose
            rng = np.random.default_rng(req.seed) if choose is Choose.RANDOM else self.rng
            pl = placer.place(g, prim, sec, rng=rng, stations=stations, choose=choose)
        except (PlacementError, MapError) as exc:
            resp.message = str(exc)
            return resp
        watched = ([prim] + sec)[pl.target_index]
        frame = self.map_frame
        r = self._rating_msg(frame, pl.position, look_at_quaternion(pl.position,
                                                                    watched.position))
        t = pl.terms
        r.rating, r.depth_of_field, r.resolution = t['rating'], t['dof'], t['res']
        r.field_visibility, r.angular_visibility = t['tfv'], t['tav']
        r.collision_probability = t['collision_p']
        resp.best = r
        resp.feasible = int(pl.extras.get('feasible', np.count_nonzero(pl.ratings > 0)))
        resp.success = True
        which = 'primary' if pl.target_index == 0 else f'secondary {pl.target_index - 1}'
        dist = float(np.linalg.norm(pl.position - watched.position))
        resp.message = f'watching the {which} target at {dist:.2f} m'
        if choose is Choose.RANDOM:
            resp.message += f' (drawn from {resp.feasible} feasible poses)'
        if pl.extras.get('freed_cells'):
            resp.message += (f"; {pl.extras['freed_cells']} occupied cell(s) at the primary "
                             'taken as free')
        return resp


def main(args: list[str] | None = None) -> int:
    """`ros2 run coop_viewplan view_planner`."""
    return run_node(ViewPlannerNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
