"""Map core: fusion maths against hand-computed cases, ray carving, OctoMap agreement, files."""
import json
import zipfile

import numpy as np
import pytest

from coop_mapping import voxelmap
from coop_mapping.gauss import (
    mat_from_sym6,
    merge_two,
    rotate_sym6,
    sym6_cholesky,
    sym6_from_cholesky,
    sym6_from_mat,
    sym6_inv,
)
from coop_mapping.octomap_peer import leaf_states
from coop_mapping.voxelmap import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    MapFileError,
    MapInputError,
    OccupancyModel,
    VoxelMap,
    pack_keys,
    ray_voxel_keys,
    state_agreement,
    unpack_keys,
)


def test_two_gaussians_merge_hand_computed():
    # 1-D along x: N(0, 1) * N(2, 1) = N(1, 0.5); y, z: sigma 1 and 2 -> 1/(1 + 1/4) = 0.8
    m, c = merge_two(np.zeros(3), np.diag([1.0, 1.0, 1.0]), np.array([2.0, 0, 0]),
                     np.diag([1.0, 1.0, 4.0]))
    assert np.allclose(m, [1.0, 0, 0])
    assert np.allclose(c, np.diag([0.5, 0.5, 0.8]))


@pytest.mark.parametrize('voxel_prior', [False, True])
def test_map_gaussian_equals_sequential_eq_3_10(voxel_prior):
    rng = np.random.default_rng(3)
    res = 0.5
    pts = rng.uniform(0.05, 0.45, (6, 3)) + np.array([2.0, 0.0, 0.0])
    covs = []
    for _ in pts:
        A = rng.normal(size=(3, 3)) * 0.02
        covs.append(A @ A.T + np.eye(3) * 1e-4)
    covs = np.array(covs)
    vm = VoxelMap(res, voxel_prior=voxel_prior)
    # two scans: three points each, so the stored (float16) Gaussian is merged again
    vm.insert_scan(pts[:3], np.zeros(3) + 0.01, covariances=sym6_from_mat(covs[:3]))
    vm.insert_scan(pts[3:], np.zeros(3) + 0.01, covariances=sym6_from_mat(covs[3:]))
    if voxel_prior:  # N(centre, V) first, then every point with C_i + V (V = res^2/12 I)
        V = np.eye(3) * res * res / 12
        mean, cov = np.array([2.25, 0.25, 0.25]), V
        for p, c in zip(pts, covs, strict=False):
            mean, cov = merge_two(mean, cov, p, c + V)
    else:
        mean, cov = pts[0], covs[0]
        for p, c in zip(pts[1:], covs[1:], strict=False):
            mean, cov = merge_two(mean, cov, p, c)
    keys, gm, gc, hits = vm.gaussians()
    assert len(keys) == 1 and hits[0] == 6
    assert np.allclose(gm[0], mean, atol=2e-4 * res)
    assert np.allclose(mat_from_sym6(gc)[0], cov, rtol=5e-3, atol=1e-8)


def test_sym6_algebra():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(20, 3, 3))
    C = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)
    s = sym6_from_mat(C)
    assert np.allclose(mat_from_sym6(sym6_inv(s)), np.linalg.inv(C))
    assert np.allclose(sym6_from_cholesky(sym6_cholesky(s)), s)
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90 deg about z
    r = rotate_sym6(sym6_from_mat(np.diag([1.0, 4.0, 9.0])[None]), R)
    assert np.allclose(mat_from_sym6(r)[0], np.diag([4.0, 1.0, 9.0]))


def test_ray_carves_hand_computed_voxels():
    # from the centre of voxel (0,0,0) to voxel (3,0,0) along x at res 1: 0,1,2 free, 3 end
    k = unpack_keys(np.unique(ray_voxel_keys(np.array([0.5, 0.5, 0.5]),
                                             np.array([[3.5, 0.5, 0.5]]), 1.0)))
    assert k.tolist() == [[0, 0, 0], [1, 0, 0], [2, 0, 0]]
    # a diagonal in the xy plane, not through corners: (0.2,0.6) -> (2.7,1.9)
    k = unpack_keys(np.unique(ray_voxel_keys(np.array([0.2, 0.6, 0.5]),
                                             np.array([[2.7, 1.9, 0.5]]), 1.0)))
    # crossings: x=1 at t=.32 (y=1.016 -> already past y=1 at t=.308), so (0,0)->(0,1)->(1,1)
    assert k[:, :2].tolist() == [[0, 0], [0, 1], [1, 1]]
    # negative direction, also across 0
    k = unpack_keys(np.unique(ray_voxel_keys(np.array([0.5, 0.5, 0.5]),
                                             np.array([[0.5, 0.5, -1.5]]), 1.0)))
    assert k.tolist() == [[0, 0, -1], [0, 0, 0]]


def _sequential_dda(o, e, res):
    """Textbook per-ray Amanatides-Woo, the way OctoMap's computeRayKeys walks."""
    key = np.floor(o / res).astype(int)
    end = np.floor(e / res).astype(int)
    d = e - o
    out = []
    if np.all(key == end):
        return out
    out.append(tuple(key))
    step = np.sign(d).astype(int)
    with np.errstate(divide='ignore'):
        tmax = np.where(step != 0, ((key + (step > 0)) * res - o) / d, np.inf)
        tdel = np.where(step != 0, res / np.abs(d), np.inf)
    while True:
        a = int(np.argmin(tmax))
        key[a] += step[a]
        tmax[a] += tdel[a]
        if np.all(key == end) or (min(tmax) > 1.0 + 1e-12 and np.all(key == end)):
            break
        if len(out) > 1000:
            raise AssertionError('runaway')
        out.append(tuple(key))
    return out


def test_batched_rays_equal_sequential_dda():
    rng = np.random.default_rng(7)
    o = rng.uniform(-1, 1, 3)
    ends = o + rng.normal(size=(200, 3)) * 2.0
    got = unpack_keys(ray_voxel_keys(o, ends, 0.1))
    want = set()
    for e in ends:
        want.update(_sequential_dda(o, e, 0.1))
    assert set(map(tuple, got.tolist())) == want


def _reference_carve(o, ends, res, end_keys):
    """Free keys by the reference closed-form traversal _ray_visits (float64, one pass)."""
    ref = np.unique(np.concatenate([voxelmap._pack_unchecked(*v)
                                    for v in voxelmap._ray_visits(o[None], ends, res)]))
    return ref[~np.isin(ref, end_keys)]


@pytest.mark.parametrize('case', ['random', 'grid_origin', 'axis_aligned'])
def test_carve_equals_reference_traversal(case):
    """The batched, octant-grouped bitmap carving (_ray_lin) visits exactly the voxels of the
    reference traversal _ray_visits: random rays in all octants and lengths, an origin on a
    grid corner (first crossing at t = 0: the clipped-count correction path) and rays that do
    not move on some axes or end on a boundary."""
    rng = np.random.default_rng({'random': 11, 'grid_origin': 12, 'axis_aligned': 13}[case])
    res = 0.125  # binary: grid coordinates below are exact
    m = 4000
    if case == 'random':
        o = rng.uniform(-1, 1, 3)
        ends = o + rng.normal(size=(m, 3)) * rng.uniform(0.02, 4.0, (m, 1))
    elif case == 'grid_origin':
        o = np.array([0.25, -0.5, 0.75])
        ends = o + rng.normal(size=(m, 3)) * rng.uniform(0.1, 3.0, (m, 1))
    else:
        o = np.array([0.25, -0.5, 0.3])
        ends = o + rng.normal(size=(m, 3)) * 2.0
        ends[: m // 3, rng.integers(0, 3)] = o[0]
        ends[m // 3: m // 2, :2] = o[:2]
        ends[m // 2: 3 * m // 4] = np.round(ends[m // 2: 3 * m // 4] / res) * res
    vm = VoxelMap(res)
    end_keys = np.unique(pack_keys(vm.key_of(ends)))
    got = vm._carve(o, ends, end_keys)
    assert got.size > 1000
    np.testing.assert_array_equal(got, _reference_carve(o, ends, res, end_keys))
    # batching does not change the set: tiny batches against one batch per octant
    k0 = np.minimum(vm.key_of(ends).min(0), vm.key_of(o[None])[0])
    dims = np.maximum(vm.key_of(ends).max(0), vm.key_of(o[None])[0]) - k0 + 1
    strides = (int(dims[1] * dims[2]), int(dims[2]), 1)
    sets = [np.unique(np.concatenate(list(voxelmap._ray_lin(o, ends, res, k0, strides,
                                                           batch_visits=bv))))
            for bv in (7, 1 << 30)]
    np.testing.assert_array_equal(sets[0], sets[1])


def test_insert_states_clamp_and_counts():
    vm = VoxelMap(0.1)
    origin = np.array([0.05, 0.05, 0.05])
    wall = np.array([[1.05, 0.05, 0.05]])
    for _ in range(20):
        vm.insert_scan(wall, origin, source='rover1')
    vm.insert_scan(wall, origin, source='rover2')
    st = vm.state_of_keys(pack_keys(np.array([[10, 0, 0], [5, 0, 0], [0, 0, 0], [20, 0, 0]])))
    assert st.tolist() == [OCCUPIED, FREE, FREE, UNKNOWN]
    p = vm.probability_at(np.array([[1.05, 0.05, 0.05], [0.55, 0.05, 0.05], [9.0, 9.0, 9.0]]))
    m = vm.model
    assert p[0] == pytest.approx(m.clamp_max, abs=1e-3)
    assert p[1] == pytest.approx(m.clamp_min, abs=1e-3)
    assert p[2] == 0.5
    assert vm.contributions == {'rover1': 20, 'rover2': 1}
    assert len(vm) == 11 and vm.bytes_per_known_voxel() <= 32
    box = vm.box_counts(np.array([0.0, 0.0, 0.0]), np.array([1.2, 0.1, 0.1]))
    assert box == {'unknown': 1, 'free': 10, 'occupied': 1}


def test_occupied_preference_and_octomap_agreement():
    octomap = pytest.importorskip('octomap')
    rng = np.random.default_rng(1)
    res = 0.1
    vm = VoxelMap(res)
    tree = octomap.OcTree(res)
    for i in range(3):
        origin = np.array([0.03 + 0.3 * i, 0.02, 1.0])
        d = rng.normal(size=(4000, 3))
        d[:, 2] = -np.abs(d[:, 2]) * 0.5 - 0.05
        d /= np.linalg.norm(d, axis=1)[:, None]
        pts = origin + d * ((0.013 - origin[2]) / d[:, 2])[:, None]
        pts = pts[np.linalg.norm(pts - origin, axis=1) < 4]
        vm.insert_scan(pts, origin)
        tree.insertPointCloud(pts, origin)
    assert state_agreement(vm.keys, vm.states(), *leaf_states(tree, res)) >= 0.995


def test_bad_input_rejected():
    vm = VoxelMap(0.1)
    with pytest.raises(MapInputError):
        vm.insert_scan(np.array([[np.nan, 0, 0]]), np.zeros(3))
    with pytest.raises(MapInputError):
        vm.insert_scan(np.zeros((3, 2)), np.zeros(3))
    with pytest.raises(MapInputError):
        vm.insert_scan(np.array([[1e6, 0, 0]]), np.zeros(3))
    with pytest.raises(MapInputError):
        VoxelMap(0.1, max_points=5).insert_scan(np.ones((6, 3)), np.zeros(3))
    with pytest.raises(ValueError):
        OccupancyModel(prob_hit=0.4)
    assert len(vm) == 0
    # a finite covariance that is not positive definite (two negative eigenvalues, det > 0;
    # one negative variance): rejected before anything changes, with or without the voxel prior
    pts = np.array([[1.05, 0.05, 0.05], [1.05, 0.25, 0.05]])
    good = np.tile([1e-4, 0, 0, 1e-4, 0, 1e-4], (2, 1))
    for prior in (True, False):
        vm = VoxelMap(0.1, voxel_prior=prior)
        vm.insert_scan(pts, np.zeros(3), covariances=good)
        before = {k: a.copy() for k, a in vm._arrays().items()}, vm.sequence
        for bad in ([-1, 0, 0, -1, 0, 1e-4], [-1, 0, 0, 1e-4, 0, 1e-4]):
            with pytest.raises(MapInputError, match='positive definite'):
                vm.insert_scan(pts + 1.0, np.zeros(3), covariances=np.vstack([good[0], bad]))
        assert vm.sequence == before[1]
        for k, a in vm._arrays().items():
            np.testing.assert_array_equal(a, before[0][k])


def test_max_range_carves_without_hit():
    vm = VoxelMap(0.1)
    vm.insert_scan(np.array([[5.05, 0.05, 0.05]]), np.array([0.05, 0.05, 0.05]), max_range=1.0)
    k = unpack_keys(vm.keys)
    assert vm.states().max() == FREE and k[:, 0].max() <= 10


def test_frustum_and_raycast():
    vm = VoxelMap(0.1)
    origin = np.array([0.05, 0.05, 0.05])
    vm.insert_scan(np.array([[1.05, 0.05, 0.05]]), origin)
    hit = vm.raycast(origin, np.array([1.0, 0, 0]), 3.0)
    assert np.allclose(hit, [1.05, 0.05, 0.05])
    assert vm.raycast(origin, np.array([0, 1.0, 0]), 3.0) is None
    R = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # optical z along map +x
    known, unknown = vm.frustum(R, origin, fov_x=0.5, fov_y=0.5, near=0.0, far=1.2)
    assert set(pack_keys(np.array([[10, 0, 0], [5, 0, 0]])).tolist()) <= set(known.tolist())
    assert len(known) == 11 and len(unknown) > 100


def test_merge_maps_equals_single_map():
    rng = np.random.default_rng(2)
    a, b, single = VoxelMap(0.1), VoxelMap(0.1), VoxelMap(0.1)
    for i in range(4):
        origin = np.array([0.0, 0.3 * i, 1.0]) + 0.01
        pts = np.column_stack([rng.uniform(1, 3, 3000), rng.uniform(-1, 2, 3000),
                               np.full(3000, 0.013)])
        (a if i % 2 else b).insert_scan(pts, origin, source=f'rover{1 + i % 2}')
        single.insert_scan(pts, origin, source=f'rover{1 + i % 2}')
    a.merge_map(b)
    assert np.array_equal(a.keys, single.keys)
    diff = np.mean(a.states() != single.states())
    assert diff <= 0.005
    assert a.contributions == single.contributions
    # Gaussians: the voxel prior counted once, as in the single map (float16 storage)
    ka, ma, ca, ha = a.gaussians()
    ks, ms, cs, hs = single.gaussians()
    assert np.array_equal(ka, ks) and np.array_equal(ha, hs)
    assert np.max(np.abs(ma - ms)) < 2e-3 * 0.1
    assert np.allclose(ca, cs, rtol=2e-2, atol=1e-7)


def test_voxel_prior_puts_the_mean_on_the_surface():
    """A plane at z = 0.013 seen along oblique rays, sigma 0.01 m along the ray and 0.001 m
    across it, in 0.1 m voxels (centre 37 mm off the plane): the literal Eq. 3-10 merge of the
    raw point covariances triangulates the nearly parallel rays and is off by ~10 mm, biased
    along the rays; with the voxel prior the mean is on the plane to a fraction of a mm."""
    rng = np.random.default_rng(5)
    n = 40_000
    origin = np.array([0.02, 0.03, 1.0])
    xy = rng.uniform(1.5, 2.5, (n, 2))
    true = np.column_stack([xy, np.full(n, 0.013)])
    d = true - origin
    d /= np.linalg.norm(d, axis=1)[:, None]
    sr, sl = 0.01, 0.001
    lat = rng.normal(size=(n, 3)) * sl
    lat -= d * np.sum(lat * d, 1)[:, None]
    pts = true + d * rng.normal(size=(n, 1)) * sr + lat
    cov = (sr ** 2 - sl ** 2) * np.einsum('ni,nj->nij', d, d) + sl ** 2 * np.eye(3)
    err = {}
    for prior in (False, True):
        vm = VoxelMap(0.1, voxel_prior=prior)
        vm.insert_scan(pts, origin, covariances=sym6_from_mat(cov))
        keys, mean, _, hits = vm.gaussians()
        surf = (unpack_keys(keys)[:, 2] == 0) & (hits >= 20)
        err[prior] = np.sqrt(np.mean((mean[surf, 2] - 0.013) ** 2))
    assert err[True] < 0.002
    assert err[False] > 0.005


def test_surface_points_hand_computed():
    """Two adjacent voxels (3 points and 1 point, no covariances) and a lone one 5 voxels
    away: each surface point is the hits x exp(-|o|^2 / 2 h^2)-weighted centroid of the means
    within the block; the lone voxel keeps its own mean."""
    vm = VoxelMap(1.0, voxel_prior=False)
    a = np.array([[0.2, 0.5, 0.5], [0.4, 0.5, 0.5], [0.3, 0.2, 0.8]])
    b = np.array([[1.7, 0.5, 0.5]])
    c = np.array([[6.5, 0.5, 0.5]])
    for p in (a, b, c):
        vm.insert_scan(p, p[0] + [0.0, 0.0, 0.2])   # origin inside the voxel: no carving
    keys, pts = vm.surface_points(bandwidth=1.0, radius=2)
    _, mean, _, hits = vm.gaussians(keys)
    assert list(hits) == [3, 1, 1]
    w = np.exp(-0.5)
    np.testing.assert_allclose(pts[0], (3 * mean[0] + w * mean[1]) / (3 + w), atol=1e-3)
    np.testing.assert_allclose(pts[1], (w * 3 * mean[0] + mean[1]) / (3 * w + 1), atol=1e-3)
    np.testing.assert_allclose(pts[2], mean[2], atol=1e-12)
    # radius 0: the voxel's own mean; a subset of keys
    k0, p0 = vm.surface_points(keys[1:2], radius=0)
    assert list(k0) == [keys[1]]
    np.testing.assert_allclose(p0[0], mean[1])
    with pytest.raises(ValueError):
        vm.surface_points(bandwidth=0.0)
    assert VoxelMap(0.1).surface_points()[1].shape == (0, 3)


def test_surface_points_undo_the_truncation_of_voxel_means():
    """A horizontal plane 8 mm below a voxel face with vertical noise of half a voxel (25 mm in
    0.05 m voxels: the points spread over three layers): the merged means of the plane's layer
    are pulled towards its centre (truncation, 12 mm RMS off the plane), the kernel surface
    points less than half as far (5 mm)."""
    rng = np.random.default_rng(7)
    res, z0, n = 0.05, 0.042, 200_000
    xy = rng.uniform(0.0, 1.0, (n, 2))
    pts = np.column_stack([xy, z0 + rng.normal(size=n) * res / 2])
    cov = np.zeros((n, 6))
    cov[:, [0, 3, 5]] = [1e-6, 1e-6, res * res / 4]
    vm = VoxelMap(res)
    vm.insert_scan(pts, np.array([0.5, 0.5, 3.0]), covariances=cov)
    keys, mean, _, _ = vm.gaussians()
    k = unpack_keys(keys)
    layer = (k[:, 2] == 0) & (k[:, 0] > 2) & (k[:, 0] < 17) & (k[:, 1] > 2) & (k[:, 1] < 17)
    _, sp = vm.surface_points(keys[layer])
    e_mean = np.sqrt(np.mean((mean[layer, 2] - z0) ** 2))
    e_surf = np.sqrt(np.mean((sp[:, 2] - z0) ** 2))
    assert e_mean > 0.010
    assert e_surf < 0.5 * e_mean


def test_save_load_roundtrip_and_corruption(tmp_path):
    rng = np.random.default_rng(4)
    vm = VoxelMap(0.1)
    vm.insert_scan(rng.uniform(1, 2, (500, 3)), np.zeros(3), source='rover1')
    path = tmp_path / 'map.cmap'
    vm.save(path)
    back = VoxelMap.load(path)
    for name in ('keys', 'logodds', 'mean_off', 'chol', 'hits'):
        assert np.array_equal(getattr(back, name), getattr(vm, name))
    assert back.sequence == vm.sequence and back.contributions == vm.contributions
    raw = path.read_bytes()
    (tmp_path / 'trunc.cmap').write_bytes(raw[:len(raw) // 2])
    with pytest.raises(MapFileError):
        VoxelMap.load(tmp_path / 'trunc.cmap')
    flipped = bytearray(raw)
    flipped[len(raw) // 2] ^= 0xFF
    (tmp_path / 'flip.cmap').write_bytes(bytes(flipped))
    with pytest.raises(MapFileError):
        VoxelMap.load(tmp_path / 'flip.cmap')
    with pytest.raises(MapFileError):
        VoxelMap.load(tmp_path / 'missing.cmap')
    assert not list(tmp_path.glob('*.tmp'))
    # a well-formed zip (CRCs right) whose header lacks a field or is not an object
    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    header = json.loads(members['header.json'])
    # ... or whose sequence / contributions do not fit the uint64 they are published as
    for bad in ({k: v for k, v in header.items() if k != 'voxels'},
                {**header, 'model': 3}, {**header, 'contributions': []}, [header],
                {**header, 'sequence': -5}, {**header, 'sequence': 2 ** 64},
                {**header, 'contributions': {'rover1': -1}}):
        with zipfile.ZipFile(tmp_path / 'hdr.cmap', 'w') as z:
            for n, data in members.items():
                z.writestr(n, json.dumps(bad) if n == 'header.json' else data)
        with pytest.raises(MapFileError):
            VoxelMap.load(tmp_path / 'hdr.cmap')


def test_a_flipped_zip_header_field_is_a_map_file_error(tmp_path):
    """One byte of a member's header in the zip's directory can name a compression method
    zipfile lacks, deflate for a stored member, or the encryption flag: zipfile then raises
    NotImplementedError, zlib.error or RuntimeError, which load turns into MapFileError."""
    import struct
    vm = VoxelMap(0.1)
    vm.insert_scan(np.array([[1.05, 0.05, 0.05]]), np.zeros(3), source='rover1')
    path = tmp_path / 'map.cmap'
    vm.save(path)
    raw = path.read_bytes()
    central = raw.find(b'PK\x01\x02')             # the first member's directory entry
    for method in (8, 12, 99):                      # deflate, bzip2 of stored data; unknown
        b = bytearray(raw)
        struct.pack_into('<H', b, central + 10, method)
        (tmp_path / 'm.cmap').write_bytes(bytes(b))
        with pytest.raises(MapFileError):
            VoxelMap.load(tmp_path / 'm.cmap')
    b = bytearray(raw)
    b[central + 8] |= 1                             # general purpose flag: encrypted
    (tmp_path / 'e.cmap').write_bytes(bytes(b))
    with pytest.raises(MapFileError):
        VoxelMap.load(tmp_path / 'e.cmap')


def test_scan_limits_are_the_mappers_input_rules():
    """`ScanLimits` is the one rule set the mapper node and coop_mapping.offline apply before
    fusing: each defect refused with its reason key; a sound scan passes."""
    from coop_mapping.voxelmap import MapInputError, ScanLimits, ScanRejected
    lim = ScanLimits(max_points=5, max_range_m=10.0)
    o = np.zeros(3)
    pts = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 3.0]])
    lim.check(pts, None, o)
    lim.check(pts, np.ones((3, 6)), o)
    cases = [(np.zeros((0, 3)), None, 'empty'), (np.ones((6, 3)), None, 'too_large'),
             (np.r_[pts, [[np.nan, 0, 0]]], None, 'nan'), (pts, np.full((3, 6), np.inf), 'nan'),
             (np.r_[pts, [[10.5, 0, 0]]], None, 'absurd_range')]
    for p, c, reason in cases:
        with pytest.raises(ScanRejected) as info:
            lim.check(p, c, o)
        assert info.value.reason == reason and isinstance(info.value, MapInputError)
    with pytest.raises(ScanRejected, match='6 points > max_points 5'):
        lim.check_count(6)
