"""Entry point of the slamkit_twoview plugin: declares ``initializer=twoview`` and its default config node."""

from __future__ import annotations

from slamkit.hookspecs import ComponentSpec, hookimpl


@hookimpl
def slamkit_components() -> list[ComponentSpec]:
    return [
        ComponentSpec(
            kind="initializer",
            name="twoview",
            target="slamkit_twoview.initializer.TwoViewInitializer",
            config={
                # ORB-SLAM2 Tracking::MonocularInitialization: new Initializer(frame, sigma=1.0, iterations=200)
                "ransac_iterations": 200,
                "sigma_px": 1.0,
                "T_H": 5.991,  # ORB-SLAM sec. IV-2: T_H = 5.99 (chi-square 95%, 2 dof)
                "T_F": 3.841,  # ORB-SLAM sec. IV-2: T_F = 3.84 (chi-square 95%, 1 dof)
                "gamma": 5.991,  # ORB-SLAM sec. IV-2: Gamma = T_H, so both models score on one scale
                # ORB-SLAM sec. IV-3: H if R_H = S_H / (S_H + S_F) > 0.45 (ORB-SLAM3's code: 0.50, ORB-SLAM2's:
                # 0.40). 0.50 sends a noise-free plane (R_H = 0.5 exactly) to F, which refuses it: the initializer
                # contract's planar problems fail with it (tests/contracts/test_initializer_contract.py)
                "rh_threshold": 0.45,
                # ORB-SLAM2 code: DLT over all 8 matches of the set; paper sec. IV-2 uses 4 of them (4 or 8)
                "h_points_per_set": 8,
                # not in ORB-SLAM (false = its exact pipeline): least-squares refit of H and F on their RANSAC
                # inliers and Sampson-error refinement of E before decomposition (see refine.py); it changes S_H,
                # S_F and R_H (issue 14). Kept on: without it the initializer contract's two-view problems are
                # refused or recovered less accurately (tests/contracts/test_initializer_contract.py)
                "refine_on_inliers": True,
                "min_parallax_deg": 1.0,  # ORB-SLAM2 Initializer::Initialize: ReconstructH/F(..., 1.0, 50)
                "min_triangulated": 50,  # same call: minTriangulated = 50
                "min_good_fraction": 0.9,  # ORB-SLAM2 ReconstructH/F: good points > 0.9 x model inliers
                "h_second_best_ratio": 0.75,  # ORB-SLAM2 ReconstructH: secondBestGood < 0.75 bestGood
                "f_similar_ratio": 0.7,  # ORB-SLAM2 ReconstructF: refuse if > 1 hypothesis has nGood > 0.7 maxGood
                "max_reproj_err_sigmas": 2.0,  # ORB-SLAM2 CheckRT: squared reprojection error <= 4 sigma^2
                "max_cos_parallax": 0.99998,  # ORB-SLAM2 CheckRT: rays with cos >= 0.99998 (~0.36 deg) not mapped
                "parallax_rank": 50,  # ORB-SLAM2 CheckRT: parallax of the 51st most-parallax good point
                "min_singular_ratio": 1.00001,  # ORB-SLAM2 ReconstructH: refuse if d1/d2 or d2/d3 < 1.00001
                # ORB-SLAM2/3 Initializer::Initialize: FindHomography and FindFundamental in two threads; slamkit
                # also grades half of the motion hypotheses in the second thread (same result either way; false:
                # everything in the calling thread)
                "parallel_models": True,
                # slamkit (not in ORB-SLAM): each hypothesis' points triangulated and graded by a compiled screen, with
                # ORB-SLAM's DLT (LAPACK's SVD) only for the points a margin cannot decide, those near the ranked
                # parallax and the points of the hypothesis kept (reconstruct.py check_motion_screened): the same
                # counts, parallax and points as false (every point by the DLT), in less time (docs/BENCHMARKS.md,
                # branch initspeed)
                "screened_grading": True,
            },
            description="ORB-SLAM's two-view map initializer: H/F model selection (sec. IV)",
        )
    ]
