"""coop_common.lockstep: the simulator's book of answers and a participant's inbox."""
from __future__ import annotations

import math

import pytest

from coop_common.lockstep import Gate, Inbox, LockstepError


def test_a_round_is_answered_when_every_participant_has_answered_it():
    g = Gate(['/slave', '/master', '/slave'])
    assert g.participants == ('/master', '/slave')
    assert g.waiting_for(0) == ['/master', '/slave']
    assert g.answer('/slave', 0, {'/rover2/cmd_vel': 1})
    assert g.waiting_for(0) == ['/master']
    with pytest.raises(LockstepError, match='not answered'):
        g.published(0)
    assert g.answer('/master', 0, {'/rover2/cmd_vel': 2, '/rover1/markers': 1})
    assert g.waiting_for(0) == []
    assert g.published(0) == {'/rover1/markers': 1, '/rover2/cmd_vel': 3}
    assert g.published(0) == {}         # handed out once


def test_the_gate_keeps_who_takes_which_topic_from_their_acks():
    g = Gate(['/slave', '/master'])
    g.answer('/slave', 0, {}, ['/rover2/joint_states', '/sim/rover2/contact'])
    g.answer('/master', 0, {}, ['/rover2/joint_states'])
    assert not g.answer('/master', 0, {}, ['/rover1/image'])   # a repeated ack: not taken in
    assert g.listeners == {'/rover2/joint_states': {'/slave', '/master'},
                           '/sim/rover2/contact': {'/slave'}}


def test_repeated_skipped_and_unknown_answers():
    g = Gate(['/slave'])
    assert g.answer('/slave', 0, {})
    assert not g.answer('/slave', 0, {})          # round 0 ticked again: ignored
    with pytest.raises(LockstepError, match='round 2 after round 0'):
        g.answer('/slave', 2, {})
    with pytest.raises(LockstepError, match='not a lockstep participant'):
        g.answer('/viewer', 1, {})
    with pytest.raises(LockstepError, match='negative'):
        g.answer('/slave', 1, {'/x': -1})
    with pytest.raises(LockstepError, match='at least one'):
        Gate([])


def test_the_inbox_hands_out_a_rounds_messages_by_stamp_then_by_topic():
    box = Inbox()
    for topic in ('/odom', '/wrench', '/joints'):
        box.listen(topic)
    with pytest.raises(LockstepError, match='twice'):
        box.listen('/odom')
    box.put('/joints', 1.0, 'j1')
    box.put('/wrench', 1.0, 'w1')
    box.put('/joints', 1.005, 'j2')
    box.put('/joints', 1.010, 'j3')          # the next round's, already here
    counts = {'/joints': 2, '/wrench': 2, '/elsewhere': 4}
    assert box.missing(counts) == {'/wrench': 1}
    with pytest.raises(LockstepError, match='on their way'):
        box.take(counts)
    box.put('/wrench', 1.005, 'w2')
    box.put('/odom', -math.inf, 'o')          # no header: first
    assert box.missing({**counts, '/odom': 1}) == {}
    assert [m for _, m in box.take({**counts, '/odom': 1})] == ['o', 'w1', 'j1', 'w2', 'j2']
    assert box.take({'/joints': 1}) == [('/joints', 'j3')]
    assert box.topics == ('/odom', '/wrench', '/joints')
