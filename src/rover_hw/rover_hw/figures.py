"""What the hardware tests measure, as they print it and as docs/results/hardware.md shows it
(coop_common.figures: the tests record, `pytest --figures-json PATH` writes, the page's blocks
are made from that file).

Keys: `hw_fuzz` (test_protocol's 10^5 damaged frames), `hw_imu`, `hw_watchdog`, `hw_replug`,
`hw_unplug`, `hw_rates` (test/test_hw_graph.py), `ident_bridge`
(test/test_hw_identification_graph.py) and `ident_sim` (test/test_identification_graph.py).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from coop_common.figures import records

#: the injector's and the decoder's counters, in the order they are printed
INJECTED = ('garble', 'bad_crc', 'partial', 'bad_version', 'drop', 'seq_gap')
REJECTED = ('bad_cobs', 'short', 'bad_crc', 'bad_version', 'unknown_type', 'bad_length',
            'oversize')


def _counts(counts: Mapping[str, int], names: tuple[str, ...]) -> str:
    return ', '.join(f'{n} {counts[n]}' for n in names if counts.get(n))


def fuzz_line(r: Mapping[str, Any]) -> str:
    """One `hw_fuzz` record: what was sent and damaged, what the decoder accepted and counted."""
    dec = r['decoder']
    return (f'fuzz: {r["frames"]} frames in reads of {r["read_bytes"][0]}-{r["read_bytes"][1]} '
            f'bytes, {r["damaged"]} damaged ({_counts(r["injected"], INJECTED)})\n'
            f'decoder: {dec["frames"]} accepted, {r["rejected"]} counted bad '
            f'({_counts(dec, REJECTED)}); {r["accepted_not_sent"]} accepted that differ from '
            f'every frame sent, {r["clean_lost"]} clean frames lost')


def format_fuzz(data: Mapping[str, Any]) -> str:
    """The `hw_fuzz` records of a figures file."""
    return '\n'.join(fuzz_line(r) for r in records(data, 'hw_fuzz'))


def imu_line(r: Mapping[str, Any]) -> str:
    """One `hw_imu` record: the IMU rate by its stamps and the share of the device frames seen."""
    return (f'imu: {r["rate_hz"]:.1f} Hz by stamps, {r["delivered"]:.1%} of the device frames '
            f'received ({r["frames"]} in {r["wall_s"]:.2f} s wall)')


def watchdog_line(r: Mapping[str, Any]) -> str:
    """One `hw_watchdog` record: how soon the wheels stopped after the last command."""
    return (f'watchdog: wheels stopped {r["stopped_after_s"] * 1e3:.0f} ms after the probe '
            f'stopped commanding ({r["observed_s"] * 1e3:.0f} ms observed)')


def replug_line(r: Mapping[str, Any]) -> str:
    """One `hw_replug` record: the arm through an unplug and a re-plug (no jump)."""
    return (f're-plug: arm_joint_1 (means of {r["n"]} readings) {r["q_unplug"]:.3f} rad at the '
            f'unplug (moving since {r["q_start"]:.3f}), {r["q_back"]:.3f} on return, '
            f'{r["q_held"]:.3f} after {r["held"]} readings; wheels {r["spin_back"]:.2f} rad/s '
            f'on return; the new trajectory went no lower than {r["low"]:.3f}, peaked at '
            f'{r["speed"]:.2f} rad/s and ended at {r["q_end"]:.3f} rad')


def unplug_line(r: Mapping[str, Any]) -> str:
    """One `hw_unplug` record: how soon the bridge reconnected."""
    return (f'unplug: bridge saw the device lost, reconnected {r["delay_s"] * 1e3:.0f} ms after '
            'the device returned')


def rates_table(r: Mapping[str, Any]) -> str:
    """One `hw_rates` record: each topic's rate by its stamps through rover_sim and the bridge."""
    rows = ['topic                          rover_sim Hz   bridge Hz   bridge/sim']
    for topic, (sim, hw) in r['rates'].items():
        ratio = f'{hw / sim:12.3f}' if sim > 0 else f'{"-":>12s}'
        rows.append(f'{topic:30s} {sim:12.2f} {hw:11.2f} {ratio}')
    return '\n'.join(rows)


_GRAPH = (('hw_imu', imu_line), ('hw_watchdog', watchdog_line), ('hw_replug', replug_line),
          ('hw_unplug', unplug_line), ('hw_rates', rates_table))


def format_graph(data: Mapping[str, Any]) -> str:
    """test_hw_graph.py's records, in the order above (a key no test of the run added, e.g. a
    deselected test's, is left out)."""
    got = data.get('records', {})
    return '\n'.join(line(r) for key, line in _GRAPH if key in got for r in got[key])


def bridge_line(r: Mapping[str, Any]) -> str:
    """One `ident_bridge` record: an identification through the emulator and the bridge."""
    return (f'{r["message"]}; {r["samples"]} samples; goal took {r["wall_s"]:.1f} s wall for '
            f'{r["duration_s"]:g} s; mean abs. rel. error {100 * r["mean_abs_rel_error"]:.1f} %')


def sim_line(r: Mapping[str, Any]) -> str:
    """One `ident_sim` record: an identification through rover_sim directly."""
    return (f'{r["message"]}; {r["samples"]} samples; mean abs. rel. error '
            f'{100 * r["mean_abs_rel_error"]:.1f} %')


def format_identification(data: Mapping[str, Any]) -> str:
    """Identifications through the emulator and bridge, then through rover_sim directly."""
    return '\n'.join(['emulator -> bridge -> identifier:',
                      *(bridge_line(r) for r in records(data, 'ident_bridge')),
                      'rover_sim -> identifier:',
                      *(sim_line(r) for r in records(data, 'ident_sim'))])
