"""Scripted motions on the world core (no rclpy) that tests and benchmarks share: the slave's
card brought level over the Table 5-1 slot and lowered into it."""
from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

from .rover_model import ARM_JOINT1_ABOVE_SENSOR_M, ARM_JOINTS, ARM_LINKS, card_ik
from .world import NOMINAL_HEIGHT_M, ContactState, World

#: joint 2 to the card's centre along the arm's heading while the card is over the slot
REACH_M = 0.30


@dataclass(frozen=True)
class CardOverSlot:
    """Rover `index` with its card level `clearance_m` above the slot's mouth; `above` is the
    card centre's height over joint 2 there (card_ik's z)."""

    index: int
    above: float
    clearance_m: float


def card_over_slot(world: World, index: int, *, offset_m: float = 0.0, away_m: float = 0.0,
                   clearance_m: float = 0.02, settle_s: float = 1.5) -> CardOverSlot:
    """Place rover `index` (its arm heading +x) so that its card hangs level `clearance_m`
    above the slot, `offset_m` along x off the slot's centre line (`away_m` further back, for
    the same motion in free space), and let it settle."""
    r2 = world.rovers[index].params.cg_to_arm
    sx, sy, top = world.layout.site.slot_centre
    joint2_z = NOMINAL_HEIGHT_M + r2[2] + ARM_JOINT1_ABOVE_SENSOR_M + ARM_LINKS[0].length
    world.place_rover(index, sx - REACH_M - r2[0] + offset_m - away_m, sy - r2[1], 0.0)
    above = top + world.layout.card.height_m / 2 + clearance_m - joint2_z
    world.command_arm(index, ARM_JOINTS, [0.2], [[0.0, *card_ik(REACH_M, above)]])
    for _ in range(int(settle_s / world.dt)):
        world.step()
    return CardOverSlot(index, above, clearance_m)


def lower_card(world: World, start: CardOverSlot, *, depth_m: float, speed_m_s: float = 0.01,
               hold_s: float = 0.0, command_period_s: float = 0.05
               ) -> Iterator[ContactState | None]:
    """Lower the card by `depth_m` at `speed_m_s`, then hold `hold_s`; the arm is re-commanded
    every `command_period_s` and keeps the card level against the base's sag from its true
    pitch (as a vision loop would). Yields each step's ContactState (World.contact)."""
    pitch = 0.0
    every = max(1, round(command_period_s / world.dt))
    for k in range(int((depth_m / speed_m_s + hold_s) / world.dt)):
        if k % every == 0:
            rot = world.card_pose(start.index)[1]
            pitch -= 0.5 * math.atan2(-rot[2, 0], rot[0, 0])
            z = start.above - min(depth_m, speed_m_s * k * world.dt)
            world.command_arm(start.index, ARM_JOINTS, [command_period_s],
                              [[0.0, *card_ik(REACH_M, z, pitch)]])
        world.step()
        yield world.contact(start.index)
