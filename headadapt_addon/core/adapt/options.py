"""What an adaptation takes and gives: its options (every tuned constant, with its reason), the
report of one level, and the result (paper sec 5: E_d, E_m, E per level)."""

from __future__ import annotations

import dataclasses

import numpy as np

from . import calibration

SCANNER_VISIBLE_PARTS = ("skin", "eye_l", "eye_r")


# the face: what the outcome judges the fit by (hair, a crown or a collar may cover scalp and neck)
FACE_REGIONS = ("forehead", "brow_l", "brow_r", "eyelid_l", "eyelid_r", "nose", "cheek_l", "cheek_r",
                "upper_lip", "lower_lip", "chin_jaw")


# the most levels after level 0 a run may ask for: the support halves per level down to the template's
# finest sample spacing (min_sample_spacing), which level 4 reaches; more levels only repeat the finest
MAX_LEVELS = 8


@dataclasses.dataclass(frozen=True)
class AdaptOptions:
    """Settings of one adaptation run (lengths in metres of the template frame)."""
    max_levels: int = 4                 # levels after level 0
    rho: float = 0.0                    # level-0 smoothing (eq 9), m
    support: float | None = None        # fixed CSRBF support sigma (m); default: support_factor x spacing
    calibration: str = "auto"           # "paper", "umeyama" or "auto"
    drop_flagged: bool = True           # drop FDPs confirmed as wrongly clicked and refit level 0
    confirm_mm: float = 10.0            # a click this far from where a coarse fit to the surface and the
                                        # other clicks puts its FDP is wrong, mm (people disagree by ~3 mm,
                                        # a coarse fit errs by ~5; a slip of the hand is 20)
    confirm_factor: float = 3.0         # ... or this x the clicks' median distance there, if larger
    off_surface_mm: float = 12.0        # an FDP farther than this from the scan surface is an error
    marker_reach_mm: float = 100.0      # a held-out marker farther than this outside the scan's box is an error
                                        # (another frame or unit; a marker may lie in a hole at the scan's edge:
                                        # a neck marker on a scan cut at the chin)
    curvature_points: int = 150         # scan curvature points at level 1 (doubles per level)
    sample_spacing: float = 0.016       # spacing of the CSRBF centres at level 1 (halves per level), m
    min_sample_spacing: float = 0.002   # finest centre spacing, m
    support_factor: float = 3.0         # CSRBF support = this x the level's spacing
    centre_density: float = 3.0         # a level's CSRBF centres lie its support / this apart
    reach_factor: float = 1.25          # closest-point pairs are kept within this x width/10 at level 1 (halving)
                                        # (1.0 until the ears weighed fully: a level that started farther off
                                        # then left skin beyond the next level's reach, unpaired: tuning head 2,
                                        # 8 clicks, 158 lip and chin vertices over 1 mm from the scan, 8 at 1.25)
    min_reach: float = 0.002            # closest-point pairs are kept within threshold/2^(k-1), at least this, m
    use_feature_mesh: bool = True       # pairs from feature-mesh subdivision (sec 4.1, Kahler et al.)
    use_curvature: bool = True          # pairs from the scan's mean-curvature search (sec 4.1, appendix)
    curvature_reach: float = 0.004      # farthest a curvature point may be from the template, m
    feature_weight: float = 1.0         # weight of a feature-mesh pair (a surface pair weighs 1)
    curvature_weight: float = 1.0       # weight of a curvature pair
    affine_iterations: int = 8          # ICP rounds of the whole-skin affine map before the clicks' RBF
    affine_weights: tuple = (("scalp", 0.0), ("forehead", 0.0))
                                        # (region, weight) in the affine map (others weigh 1): the skull's
                                        # shape above the brows differs among people in ways no affine map
                                        # follows (a sloping forehead, a long skull); fitted to it the map
                                        # tilted the whole face a few degrees, more with every round. (The
                                        # posed neck pulls too: at 0.25 the tuning heads gained, but the
                                        # real CT's face lay 1.08 mm from its skin instead of 0.83)
    affine_along_normal: bool = True    # the affine map's pairs lie along the template's normals (rays),
                                        # not at closest points: no sideways pull on the face
    affine_both_pairings: bool = True   # fit the affine map both ways (pairs along the normals and at the
                                        # closest points) and keep the one whose skin lies nearer the scan
                                        # (level0.affine_scan_distance): either pairing alone lost some
                                        # heads by a millimetre (docs/MEASUREMENTS.md)
    pair_weights: tuple = (("ear_l", 1.0), ("ear_r", 1.0))
                                        # (region, weight) of the skin's surface pairs where it differs from
                                        # the region's weight in E_d (the paper's ears 0.2, sec 5.1): the ears
                                        # are what holds the side of the face in place (seen on tuning head
                                        # 42: the template ear 17 mm off, the cheek beside it 10 mm). At full
                                        # weight, tuning heads 0-35: correspondence -0.083 mm paired (58 of 72
                                        # better), seeds 36-49 -0.155 (23 of 28); surface unchanged
    affine_distance_clip: float = 0.005 # a vertex farther than this from the scan counts as this far, m
    affine_ridge: float = 1e-3          # how firmly the affine map's linear part is held to the identity
    rays_from_level: int = 2            # from this level on, pairs along the template's normal (sec 4.1)
    fold_rounds: int = 2                # refits of a level without pairs around the triangles it folded
    blend_back_rings: tuple = (1, 2, 3, 4, 6, 8, 12, 16)
                                        # a level's folds may be repaired by the level below on their corners,
                                        # the level's offset back in linearly over this many rings (the
                                        # narrowest that folds nothing), when that leaves the skin nearer the
                                        # scan than relaxing them (unfolding.py)
    icp_iterations: int = 3             # pairing and refit rounds per level (the least, for closest-point levels)
    icp_settle: float = 5e-5            # a closest-point level (below rays_from_level) goes on past them until a
                                        # round moves the skin less than this RMS, m: its pairs slide the skin
                                        # a little each round, and the third round still moved it 0.2 to 0.4 mm
                                        # (tuning heads 0-35: correspondence -0.041 mm, 52 of 72 cases better,
                                        # with fine_icp_iterations; docs/MEASUREMENTS.md)
    icp_max_rounds: int = 16            # ... but no more rounds than this
    fine_icp_iterations: int = 2        # rounds of the levels from fine_from_level on (rays, which do not
    fine_from_level: int = 3            # slide the skin: the third round changed little, and these levels cost most)
    stiffness: float = 10.0             # smoothness of a level: ridge on its CSRBF coefficients, relative
                                        # to the data weight a centre carries (nricp's stiffness, in effect)
    stiffness_decay: float = 0.2        # the stiffness per level falls by this factor
    min_stiffness: float = 0.0          # down to this
    robust_scale: float = 0.5           # Cauchy weight scale of a surface pair, x the level's reach
    click_weight: float = 20.0          # a click weighs as much as this many surface pairs at level 1
    click_decay: float = 0.25           # and this factor less at each finer level (evidence, not law)
    seam_band: float = 0.0015           # no pairs within this of the inner-lip seam (template frame), m: a ray
                                        # there may land on the other lip (4 mm, the first value, left half the
                                        # lip red unpaired: seen-face surface RMS 0.32 against 0.27 mm on tuning
                                        # heads; 1 mm fitted as well but turned legacy head 3's smile key)
    snap_reach: float = 0.002           # the last step lays each seen vertex onto the scan along its normal
                                        # within this (snap.py), m; 0: no snap. Tuning heads 0-11, 8 and 11
                                        # clicks: surface 0.257 -> 0.220 mm (median; better on 22, the same on 2),
                                        # correspondence -0.001 mm (better on 18), markers the same
    snap_smooth: float = 0.1            # ... stretching its displacement over each skin edge with this weight
                                        # against 1 on each vertex's distance (0.03 to 1 tried: 0.1 nearest)
    snap_keep: tuple = ("eye_socket_l", "eye_socket_r")
    snap_keep_rings: int = 5            # ... but not the skin within this many rings of these regions (the
                                        # lids' margins): snapped, a blink left up to 38% of the eyeball seen
                                        # at rest showing, not 19% (`./ha bench expressions --lids t,0-11`;
                                        # kept so: 21%, surface on tuning heads 0-11 0.220 mm, not 0.214)
    snap_fold_rounds: int = 5           # ... solved again with wider pins round what it would fold
    alpha: float = 1.0                  # weight of E_d in E (eq 24)
    beta: float = 0.01                  # weight of E_m in E (E_m sums over markers, E_d averages)
    stop_at_minimum: bool = False       # stop when E rises (sec 5.3); all levels run and the least E is
                                        # kept instead: on a face-only scan E rose 0.2% at level 1 and the
                                        # paper's stop kept level 0, 1.6 mm off the scan (level 4: 0.33 mm)
    anatomy_support: float = 0.024      # bone, eyes and pivots follow the levels of at least this support, m
    bad_fit_rms_mm: float = 1.5         # seen-skin distance RMS above this is a failed fit: 3x the
                                        # noise of a range scanner (0.1-0.5 mm), mm
    beyond_mm: float = 5.0              # a scan point by the face or ears this far outside the adapted skin is
    beyond_pct: float = 1.5             # scan the fit did not reach; over this share of them, a warning, mm and %
                                        # (an ear's rim left 9-14 mm out: 2.4-4.6% on 4 of 60 generated heads,
                                        # the others and the real scans at most 0.6%; outcome.scan_beyond)
    dense_spacing: float = 0.0025       # a scan whose median edge is shorter is paired by its vertices'
                                        # tangent planes (off by curvature x spacing^2 / 2), not closest points,
                                        # m. 2.5 mm: the scan-like bench heads (about 2 mm edges) fit as closely
                                        # as with closest points (tuning heads: correspondence +0.001 mm, surface
                                        # 0.271 against 0.279 mm), those 2 mm left on closest points in 0.79-0.86
                                        # the time. 3 mm also took the CT (2.56 mm edges) and left a lid vertex
                                        # of it 0.7 mm inside its transferred skull
    scan_cell: float = 0.001            # a scan whose median edge is under this is clustered to a grid of it
                                        # first (mesh/simplify.py), m; 0: never. Half the finest centre spacing:
                                        # the 1M bench head (0.77 mm edges) keeps 252k clusters and fits as
                                        # closely in half the time (./ha bench scale --accuracy)
    jacobi_steps: int = 250             # a level's solve factorises (sparse LU) after this many diagonal-
                                        # preconditioned CG steps (face-only scans need ~800)
    lu_steps: int = 30                  # ... and refactorises when CG preconditioned by that LU takes more
    solve_rtol: float = 1e-5            # relative residual of a level's solve (1e-3 fitted the skin as well,
                                        # 19% faster, but the skull pressed under that skin folded 23 triangles
                                        # instead of 9 on legacy head 7: the transfer is that sensitive)
    backend: str = "numpy"              # spatial queries: "numpy" (core/mesh/bvh.py: exact, no Blender, as fast
                                        # as Blender's), "embree" (rays by Intel Embree, the embreex package,
                                        # measured again in float64: the adaptation in about 0.8 of the time)
                                        # or "bvh" (Blender's mathutils BVH: in Blender or beside the bpy
                                        # module); the same answers up to float32 rounding and tie-breaks


@dataclasses.dataclass
class Level:
    """The report of one level: pairs used, errors (mm^2 as in the paper, RMS mm), seconds."""
    level: int
    method: str
    pairs: int
    new_pairs: int
    E_d: float
    E_d_rms_mm: float
    E_m: float | None
    E: float
    coverage: float
    seconds: float
    support_mm: float | None = None


@dataclasses.dataclass
class AdaptResult:
    """The adapted skin and everything needed to carry anatomy along (template frame unless named)."""
    verts: np.ndarray                 # (n,3) adapted skin, template frame, metres
    verts_scan: np.ndarray            # (n,3) adapted skin in the scan's frame and unit
    similarity: calibration.Similarity  # scan frame -> template frame
    levels: list
    best_level: int
    functions: list                   # level functions, each x (template) -> displacement
    flagged: dict                     # FDP id -> reason
    dropped: list
    calibration_info: dict
    seconds: float
    distances: np.ndarray             # (n,) distance of each adapted skin vertex to the scan, m (nan: no match)
    scan: object = None               # the calibrated scan (template frame) with its queries
    unfolded: dict = None             # folded triangles after the fit, vertices moved, folds left, repair
    snapped: dict = None              # the last step's pairs, pins and rounds (snap.py); None: not run
    outcome: dict = None              # how it ended: folds left, seen-skin RMS, marker RMS, warnings, ok
    anatomy_support: float = 0.0      # map_points uses the levels with at least this support, m
    backend: str = "numpy"            # the spatial backend of the fit (AdaptOptions.backend), for the transfer
    stages: dict = None               # seconds per stage: calibrate, prepare (the scan's queries, normals,
                                      # curvature), level_0.., unfold (with the exact distances reported and
                                      # the scan not reached: outcome.scan_beyond)

    def map_points(self, points):
        """Carry template-frame points (k,3) inside the head (bone, eyes, pivots) through the
        adaptation map (template frame): the levels whose support reaches under the skin
        (AdaptOptions.anatomy_support); the finer ones shape the skin's surface only, and would
        bend bone a few millimetres under it (anatomy.keep_inside keeps the bone under the skin)."""
        points = np.asarray(points, dtype=np.float64)
        return points + sum(f(points) for f in self.functions
                            if getattr(f, "sigma", np.inf) >= self.anatomy_support)

    def to_scan(self, points):
        """Template-frame points (k,3) into the scan's frame and unit."""
        return self.similarity.inverse().apply(points)

    def report(self):
        """A JSON-ready dict: per level pairs/E_d/E_m/E/seconds, totals, flagged FDPs."""
        return {
            "levels": [dataclasses.asdict(lv) for lv in self.levels],
            "best_level": self.best_level,
            "stopped_because": (f"E reached its minimum at level {self.best_level}"
                                if self.best_level < self.levels[-1].level else "last level reached"),
            "seconds": self.seconds,
            "stage_seconds": self.stages or {},
            "spatial_backend": self.backend,
            "calibration": self.calibration_info,
            "flagged_fdps": self.flagged,
            "dropped_fdps": self.dropped,
            "unfolded": self.unfolded,
            "snapped": self.snapped,
            "outcome": self.outcome,
            "units": "E_d, E_m, E in mm^2 of the template frame (paper eq 22-24); *_mm in mm",
        }
