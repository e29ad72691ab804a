"""coop_common.testing's choice of a ROS domain: the domains a DDS participant on this machine
holds, read from the kernel's UDP tables, are skipped."""
import rclpy
from rclpy.context import Context

from coop_common.testing import domains_in_use, free_domain_id, pick_domain_id

HEADER = ('  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  '
          'timeout inode ref pointer drops\n')


def _row(port: int) -> str:
    return f'   1: 0100007F:{port:04X} 00000000:0000 07 00000000:00000000 00:00000000 0 0 0\n'


def test_domains_in_use_are_read_from_the_rtps_ports(tmp_path):
    table = tmp_path / 'udp'
    # domain 3's unicast discovery and user ports (participants 0 and 2), domain 100's last
    # participant; below domain 1, the multicast base of a domain and an ephemeral port: none
    ports = [7400 + 250 * 3 + 10, 7400 + 250 * 3 + 15, 7400 + 250 * 100 + 249, 7410, 5353,
             7400 + 250 * 7, 40000]
    table.write_text(HEADER + ''.join(_row(p) for p in ports))
    assert domains_in_use([str(table), str(tmp_path / 'absent')]) == {3, 100}


def test_free_domain_id_skips_the_taken_ones_and_gives_workers_their_own():
    assert free_domain_id(41, in_use=set()) == 42 == pick_domain_id(41)
    assert free_domain_id(41, in_use={42, 43}) == 44
    assert free_domain_id(41, nth=1, in_use={42, 43}) == 45
    assert free_domain_id(99, in_use={100}) == 1           # it wraps within 1..100
    assert free_domain_id(5, in_use=set(range(1, 101))) == pick_domain_id(5)


def test_a_running_participant_makes_its_domain_taken():
    domain = free_domain_id()
    assert domain not in domains_in_use()
    context = Context()
    rclpy.init(context=context, args=[], domain_id=domain)
    try:
        node = rclpy.create_node('domain_probe', context=context)
        assert domain in domains_in_use()
        assert free_domain_id(domain - 1) != domain
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
