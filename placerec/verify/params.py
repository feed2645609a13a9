"""Parameters of the verification stage: one strict `Params` model per step, composed in `VerifyParams`.

Defaults come from the ISHOT paper (Guo et al. 2019, Sec. V: minimum cluster size 8, consensus resolution 7 m,
eps_ICP 7 m^2, voxel 0.4 m) where it gives a value, otherwise from the measurements in ``docs/verification.md``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from placerec.params import Params

__all__ = ["RansacParams", "ConsistencyParams", "IcpParams", "ScoreParams", "RefineParams", "VerifyParams"]


class RansacParams(Params):
    """RANSAC over minimal samples with closed-form Kabsch (6-DoF, 3 points) or yaw (4-DoF, 2 points) solutions."""

    mode: Literal["6dof", "4dof"] = Field(
        "6dof", description="6dof: full rigid pose; 4dof: x, y, z and yaw only (gravity-aligned sensors)"
    )
    inlier_threshold: float = Field(
        0.6, gt=0, description="m; residual |T src - dst| of an inlier (ours: 1.5 x the paper's 0.4 m voxel)"
    )
    confidence: float = Field(
        0.999, gt=0, lt=1, description="probability of drawing one all-inlier sample before stopping"
    )
    max_iterations: int = Field(
        1000,
        ge=1,
        le=1_000_000,
        description="most hypotheses drawn (enough for 99.9 % confidence down to 19 % inliers)",
    )
    min_inliers: int = Field(
        8,
        ge=2,
        description="fewer inliers: no pose, rejected before ICP (ours; the paper's minimum cluster 8)",
    )
    seed: int = Field(0, description="random generator seed (runs are deterministic)")


class ConsistencyParams(Params):
    """Geometric consistency grouping (ISHOT paper Sec. IV-F / PCL ``GeometricConsistencyGrouping``)."""

    enabled: bool = Field(
        False, description="group the correspondences before RANSAC (the ISHOT paper's 3D pipelines do)"
    )
    consensus_resolution: float = Field(
        7.0, gt=0, description="m; ISHOT paper Sec. V ('consensus set resolution')"
    )
    min_cluster_size: int = Field(8, ge=1, description="ISHOT paper Sec. V ('minimum cluster size')")
    max_clusters: int = Field(
        1,
        ge=1,
        description="RANSAC runs on each of the largest clusters, up to this many; the best pose is kept",
    )


class IcpParams(Params):
    """Point-to-plane ICP between the voxelised scans (``docs/verification.md`` says why small_gicp)."""

    backend: Literal["small_gicp", "open3d", "open3d_t"] = Field(
        "small_gicp",
        description="small_gicp (measured fastest), open3d (legacy pipelines), open3d_t (tensor)",
    )
    method: Literal["plane", "gicp"] = Field(
        "plane",
        description="plane: point-to-plane (ISHOT paper Sec. IV-F); gicp: small_gicp's generalised ICP",
    )
    voxel_size: float = Field(
        0.4, gt=0, description="m; voxel grid of the match (target) scan, ISHOT paper Sec. V-B"
    )
    source_voxel_size: float = Field(
        1.5,
        gt=0,
        description="m; voxel grid of the query (source) scan: its size sets the ICP cost per candidate",
    )
    max_range: float | None = Field(
        None,
        gt=0,
        description="m; points farther from the sensor are dropped before voxelising (None keeps all)",
    )
    normal_neighbors: int = Field(10, ge=3, le=1000, description="neighbours for normals / covariances")
    max_correspondence_distance: float = Field(1.0, gt=0, description="m; ICP correspondence gate")
    max_iterations: int = Field(30, ge=1, le=10_000, description="ICP iterations at most")
    num_threads: int = Field(1, ge=1, le=1024, description="threads of the ICP backend")
    prepare_threads: int | None = Field(
        None,
        ge=1,
        le=1024,
        description="threads preparing a cloud (search tree, normals / covariances); results do not depend on "
        "it; None: OMP_NUM_THREADS when set, else the cores this process may use",
        json_schema_extra={"runtime": True},  # not recorded by a saved database: results do not depend on it
    )
    stats_points: int = Field(
        1000,
        ge=1,
        description="query voxels (evenly strided) on which fitness, RMSE and residual are measured",
    )


class ScoreParams(Params):
    """The verified score and the acceptance rule (``docs/verification.md``, 'The verified score')."""

    inlier_scale: float = Field(
        10.0, gt=0, description="inlier term 1 - exp(-inliers / scale): 0.63 at 10 inliers, 0.95 at 30"
    )
    fitness_distance: float = Field(
        0.5,
        gt=0,
        description="m; a query voxel overlaps when its nearest match voxel is this close after ICP",
    )
    min_score: float = Field(0.25, ge=0, le=1, description="accept when score >= min_score (measured)")
    acceptance: Literal["score", "eps_icp", "both"] = Field(
        "score", description="score: min_score; eps_icp: the ISHOT paper's rule; both: both must hold"
    )
    eps_icp: float = Field(
        7.0, gt=0, description="m^2; ISHOT paper Sec. V: accept when the ICP residual is below eps_ICP"
    )
    min_fitness: float | None = Field(
        None,
        ge=0,
        le=1,
        description="accept only when the ICP fitness (share of query voxels overlapping the match) is at least this,"
        " whatever the rule (None: no overlap gate; docs/localization.md measures 0.7 for neighbourhood targets)",
    )
    min_fitness_ratio: float | None = Field(
        None,
        gt=0,
        le=1,
        description="accept only when the ICP fitness reaches this share of what a right alignment overlaps at the "
        "candidate's displacement d (the translation of T_match_query): expected_fitness * exp(-d / "
        "expected_fitness_length_m), whatever the rule (None: not tested; docs/verification.md, 'Overlap expected "
        "at a displacement')",
    )
    expected_fitness: float = Field(
        0.75,
        gt=0,
        le=1,
        description="the fitness of a right alignment of two scans taken at the same place (d = 0); default: the "
        "VLP-16 tuning cells' right candidates (docs/sensors.md)",
    )
    expected_fitness_length_m: float = Field(
        17.5,
        gt=0,
        allow_inf_nan=False,
        description="m; the displacement over which a right alignment's expected fitness falls by a factor e; "
        "default: the VLP-16 tuning cells' right candidates (docs/sensors.md)",
    )
    eps_icp_max_range: float | None = Field(
        None,
        gt=0,
        description="m; nearest-neighbour distances beyond this are left out of the eps_ICP residual (None: PCL's"
        " getFitnessScore default, all points)",
    )
    min_constraint: float | None = Field(
        None,
        ge=0,
        le=1 / 3,
        description="accept only when the overlap pins the translation down in every direction: the smallest "
        "eigenvalue of the mean outer product of the normals of the match voxels the query overlaps after ICP "
        "(placerec.verify.icp.alignment_stats; 1/3 for normals spread evenly, ~0 for road and one facade, along "
        "which ICP slides), whatever the rule (None: not tested)",
    )


class RefineParams(Params):
    """The pose of an accepted candidate refined for the pose graph or the fix that uses it (``docs/verification.md``,
    'The accepted pose refined'): one more ICP from the judged pose, the query on a grid finer than its
    ``icp.source_voxel_size`` (``voxel_size``). It runs only after acceptance and changes the pose alone: which
    candidates are accepted, their scores and statistics are the judged ICP's."""

    enabled: bool = Field(False, description="refine the pose of every accepted candidate")
    voxel_size: float = Field(
        1.0,
        gt=0,
        allow_inf_nan=False,
        description="m; the query's voxel grid in the refinement, made once per query from the points its ICP "
        "grid was made from; never finer than icp.voxel_size (the match's); from icp.source_voxel_size up, the "
        "query's own grid is used",
    )
    method: Literal["plane", "gicp"] = Field(
        "gicp", description="gicp: small_gicp's generalised ICP; plane: point-to-plane, as the judged ICP"
    )
    max_correspondence_distance: float = Field(
        0.5, gt=0, allow_inf_nan=False, description="m; correspondence gate of the refinement"
    )
    max_iterations: int = Field(
        10,
        ge=1,
        le=10_000,
        description="ICP iterations at most: from the judged pose GICP settles within ~10 (a real HDL-64 pair: the "
        "pose after 10 and after 100 the same to 1e-12 m, where small_gicp kept iterating to the cap)",
    )
    max_shift: float = Field(
        0.3,
        gt=0,
        allow_inf_nan=False,
        description="m; a refined pose whose translation moved farther than this from the judged one is not "
        "used (the judged pose is kept); chosen on the sensors' tuning cells (tools/eval_refine_shift.py): it "
        "keeps every refinement of a right place in town and industrial, and in campus bounds the forward-looking "
        "sensors' worst pose at the same typical accuracy as 0.5",
    )


class VerifyParams(Params):
    """All parameters of `placerec.verify.verify`."""

    ransac: RansacParams = Field(default_factory=RansacParams, description="robust pose from correspondences")
    consistency: ConsistencyParams = Field(
        default_factory=ConsistencyParams, description="consistency grouping"
    )
    icp: IcpParams = Field(default_factory=IcpParams, description="refinement")
    score: ScoreParams = Field(default_factory=ScoreParams, description="acceptance")
    refine: RefineParams = Field(
        default_factory=RefineParams, description="the accepted pose refined on a finer query grid"
    )
    min_correspondences: int = Field(
        3, ge=2, description="fewer correspondences (after grouping) than this: rejected without ICP"
    )
    icp_only_coarse_distances: list[float] = Field(
        default_factory=lambda: [4.0],
        description="m; ICP without correspondences (a rough guess, e.g. Scan Context's yaw with no translation)"
        " first runs with these correspondence gates, then with icp.max_correspondence_distance (measured: a"
        " 4 m stage makes yaw-only guesses 3-4 m off converge)",
    )
    icp_only_coarse_voxel_size: float | None = Field(
        None,
        gt=0,
        description="m; the query's voxel grid in those coarse stages (made from icp.source_voxel_size's voxels;"
        " None: icp.source_voxel_size); only the last stage, at icp.max_correspondence_distance, sets the pose"
        " judged",
    )

    icp_only_fine_distances: list[float] = Field(
        default_factory=list,
        description="m; ICP from a rough guess: after the stage at icp.max_correspondence_distance, stages with"
        " these gates, each from the last one's pose; the last sets the pose judged (none: that stage does)",
    )
    icp_only_min_coarse_fitness: float | None = Field(
        None,
        ge=0,
        le=1,
        description="ICP from a rough guess: rejected without the fine stage when the coarse stages end with less"
        " overlap (score.fitness_distance) than this (None: always refined)",
    )

    @model_validator(mode="after")
    def _check(self) -> VerifyParams:
        if self.icp.method == "gicp" and self.icp.backend != "small_gicp":
            raise ValueError("icp.method 'gicp' needs icp.backend 'small_gicp'")
        if self.refine.enabled and self.refine.method == "gicp" and self.icp.backend != "small_gicp":
            raise ValueError("refine.method 'gicp' needs icp.backend 'small_gicp'")
        for name in ("icp_only_coarse_distances", "icp_only_fine_distances"):
            if any(not d > 0 for d in getattr(self, name)):
                raise ValueError(f"{name} must be positive distances")
        return self
