"""The stages of ``python -m cell.run`` on checked inputs, filling the report as they go.

Perception (or the given poses) and pose repair give the target assembly (assembly frame: metres, +z up, floor at
z = 0); the sequence planner orders it; :mod:`cell.plan` lays out the kit and plans and times every pick and
place; :mod:`cell.simulate` executes the program with physics and measures every part's final error; the
program is checked against the Panda's limits before anything is written.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cell.errors import (
    EXIT_DISAGREES,
    EXIT_OK,
    EXIT_PLANNING,
    EXIT_SIMULATION,
    BadInput,
    BadPicture,
    BadTarget,
    StageFailed,
)
from cell.inputs import Parts
from cell.report import assembly_with_poses, pose_json
from cell.scene import Scene
from planning.assembly import Assembly, AssemblyPart
from planning.collision import MAX_FITTING_OVERLAP_M
from planning.payload import DEFAULT_DENSITY_KG_M3
from planning.pose import Pose

# a predicted assembly agrees with its picture from this silhouette IoU on, where its drawing also explains this share
# of the picture's edges inside the object (perception.agreement; calibrated by benchmarks/picture_agreement.py)
MIN_SILHOUETTE_IOU = 0.80
MIN_EDGE_RECALL = 0.85
REPAIR_GIVEN_POSES = False  # given (--poses) targets are taken as they are; predicted ones are repaired
MAX_BELOW_FLOOR_M = 0.001  # given targets may reach this far under the floor (z = 0; rounding, a model's feet)
ANIMATION_FRAME_S = 0.4  # simulated seconds between the frames of animation.gif
ANIMATION_FPS = 10.0  # its playback: 4x the simulated speed


def crossing_failure(overlapping_pairs: tuple[tuple[str, str, float], ...], max_overlap_m: float,
                     max_translation_m: float) -> tuple[str, str] | None:
    """Why the repaired targets cannot be built, when two parts still overlap by more than ``max_overlap_m``
    (metres): (the message, naming the deepest such pair and how many more; the first part of that pair), None
    when none does. Such parts cross (a panel through a panel), which no cell builds; the repair moved no crossed
    part more than ``max_translation_m``."""
    deep = [pair for pair in overlapping_pairs if pair[2] > max_overlap_m]
    if not deep:
        return None
    a, b, depth = deep[0]
    more = f" (and {len(deep) - 1} more pair(s) by over {max_overlap_m * 1000:.0f} mm)" if len(deep) > 1 else ""
    return (f"after repair {a!r} and {b!r} still overlap by {depth * 1000:.0f} mm{more}: the prediction puts them "
            f"through each other, deeper than the repair (at most {max_translation_m * 1000:.0f} mm per crossed part) "
            f"can undo, and no cell builds parts through each other", a)


def indented(text: str, prefix: str) -> str:
    """``text`` with every line after the first prefixed by ``prefix`` (a failure's further lines under its first)."""
    return text.replace("\n", "\n" + prefix)


class Pipeline:
    def __init__(self, scene: Scene, parts: Parts, image: np.ndarray | None, given: dict[str, Pose] | None,
                 args: argparse.Namespace, console, report: dict,
                 given_density_kg_m3: dict[str, float] | None = None) -> None:
        self.scene, self.parts, self.image, self.given = scene, parts, image, given
        self.args, self.console, self.report = args, console, report
        # the parts' material (kg/m3): their weight in the payload check, the planner's torque checks and the
        # simulation; a part of known mass (--masses, cell.inputs.load_masses) has that mass spread over its volume
        self.density_kg_m3 = args.density or DEFAULT_DENSITY_KG_M3
        self.given_density_kg_m3 = dict(given_density_kg_m3 or {})
        self.part_density_kg_m3 = {name: self.given_density_kg_m3.get(name, self.density_kg_m3)
                                   for name in parts.names}
        self.target: Assembly | None = None
        self.prediction = None  # perception.predict.Prediction, for a run from a picture
        self.agreement = None  # perception.agreement.PictureAgreement of the repaired targets with the picture
        self.object_mask: np.ndarray | None = None  # (224, 224) bool: the object in the picture
        self.plan = None
        self.world_from_target: Pose | None = None  # the target's assembly frame on the jig, once planned
        self.simulation = None
        self.samples = None
        self.points = None  # the motions' controller points, checked
        self.entries = {name: {"name": name, "order": None} for name in parts.names}
        report["parts"] = list(self.entries.values())

    # --- 1-2: target poses ------------------------------------------------------------------------------------
    def targets(self) -> None:
        if self.given is not None:
            with self.console.stage("perception", "skipped (--poses gives the target poses)"):
                poses = dict(self.given)
            self.report["perception"] = {"source": "poses file"}
        else:
            with self.console.stage("perception", "poses from the image"):
                poses = self._predict()
        self.set_targets(poses)
        if self.prediction is not None:
            self._check_picture_agreement()

    def set_targets(self, poses: dict[str, Pose]) -> None:
        """The target assembly from every part's pose (assembly frame, metres): given poses checked for overlaps,
        predicted ones repaired. Raises :class:`BadTarget` for given poses that overlap, a target out of reach or a
        part too heavy; :class:`StageFailed` (exit 3, stage "repair") for repaired targets that still cross, with
        ``self.target`` set to them so that ``overview.png`` shows them."""
        assembly = Assembly(self.parts.files[0].parent.parent.name or "object",
                            [AssemblyPart(n, m, poses[n], f"parts/{f.name}")
                             for n, m, f in zip(self.parts.names, self.parts.meshes, self.parts.files)])
        if self.given is not None:
            self._check_given_targets(assembly)
        with self.console.stage("repair", "contacts, interpenetration, alignment"):
            assembly, crossed = self._repair(assembly)
        for part in assembly.parts:
            self.entries[part.name]["target_assembly_from_part"] = pose_json(part.assembly_from_part)
            self.entries[part.name]["target_world_from_part"] = pose_json(
                self.scene.fixture.world_from_assembly @ part.assembly_from_part)
        if crossed is not None:
            self.target = assembly
            raise StageFailed(EXIT_PLANNING, "repair", *crossed)
        from cell.plan import out_of_reach, part_masses_kg, too_heavy

        far = out_of_reach(self.scene, assembly)
        if far:
            name, distance = far[0]
            raise BadTarget(f"part {name!r}: its target on the jig is {distance:.2f} m from the robot's shoulder, out "
                            f"of the Panda's reach; scale the object down (--units) or move the jig "
                            f"([fixture] world_from_assembly in the scene file)")
        payload_kg = self.scene.robot.payload_kg
        masses = part_masses_kg(assembly, self.density_kg_m3, self.part_density_kg_m3)
        for name, kg in masses.items():
            self.entries[name].update(mass_kg=kg, density_kg_m3=self.part_density_kg_m3[name],
                                      mass_from="--masses" if name in self.given_density_kg_m3 else "--density")
        heavy = too_heavy(masses, payload_kg)
        if heavy:
            name, kg = heavy[0]
            others = f" (and {len(heavy) - 1} more)" if len(heavy) > 1 else ""
            density = self.part_density_kg_m3[name]
            weight = (f"its given mass is {kg:.1f} kg (--masses)" if name in self.given_density_kg_m3 else
                      f"it weighs {kg:.1f} kg ({kg / density * 1000:.1f} litres at {density:.0f} kg/m3, --density)")
            raise BadTarget(f"part {name!r}{others}: {weight}, more than the Panda's rated payload of "
                            f"{payload_kg:g} kg ([robot] payload_kg in the scene file); give the parts' real density "
                            "or masses (--masses) if they are lighter, scale the object down or split the part")
        self.target = assembly

    def _predict(self) -> dict[str, Pose]:
        from perception.agreement import MAX_PIXEL_NOISE, holds_an_object, object_mask, pixel_noise
        from perception.predict import PredictionError, predict

        where = self.report["inputs"]["image"] or "the picture"
        noise = pixel_noise(self.image)  # before the network: noise holds no object to predict
        if noise > MAX_PIXEL_NOISE:
            raise BadPicture(f"{where}: the picture looks like noise (neighbouring pixels differ by {noise:.0f} of 255 "
                             f"on median, a photo by a few); give a picture of the assembled object")
        try:
            prediction = predict(self.image, dict(zip(self.parts.names, self.parts.meshes)),
                                 checkpoint=self.args.checkpoint)
        except PredictionError as exc:
            raise BadInput(str(exc)) from exc
        self.report["perception"] = prediction.summary()
        self.prediction = prediction
        mask, source = object_mask(self.image, prediction.foreground)
        self.object_mask, self.report["perception"]["object_mask"] = mask, source
        if not holds_an_object(mask):
            raise BadPicture(f"{where}: no object found in the picture (it covers {100 * mask.mean():.1f}% of it, by "
                             f"the {source}); give a picture of the assembled object, filling much of the frame")
        for name in self.parts.names:
            self.entries[name]["predicted_camera_from_part"] = pose_json(prediction.camera_from_part[name])
            self.entries[name]["predicted_assembly_from_part"] = pose_json(prediction.assembly_from_part[name])
        return dict(prediction.assembly_from_part)

    def _check_picture_agreement(self) -> None:
        """The repaired targets drawn with the picture's camera against the object in the picture
        (:mod:`perception.agreement`): below :data:`MIN_SILHOUETTE_IOU` or :data:`MIN_EDGE_RECALL` the run stops
        (exit 5) unless ``--accept-prediction`` asks to build it anyway."""
        from perception.agreement import picture_agreement

        camera_from_assembly = self.prediction.camera_from_assembly
        agreement = picture_agreement(self.object_mask, self.target.part_names,
                                      [p.mesh for p in self.target.parts],
                                      [camera_from_assembly @ p.assembly_from_part for p in self.target.parts],
                                      image=self.image)
        self.agreement = agreement
        shortfalls = []
        if agreement.silhouette_iou < MIN_SILHOUETTE_IOU:
            shortfalls.append(f"silhouette IoU {agreement.silhouette_iou:.2f} < {MIN_SILHOUETTE_IOU:.2f}")
        if agreement.edge_recall < MIN_EDGE_RECALL:
            shortfalls.append(f"it explains {100 * agreement.edge_recall:.0f}% of the picture's edges < "
                              f"{100 * MIN_EDGE_RECALL:.0f}%")
        agrees = not shortfalls
        accepted = self.args.accept_prediction
        self.report["picture_agreement"] = {**agreement.to_dict(), "min_silhouette_iou": MIN_SILHOUETTE_IOU,
                                            "min_edge_recall": MIN_EDGE_RECALL, "agrees": agrees,
                                            "accepted_anyway": accepted and not agrees}
        for name, fraction in agreement.on_object.items():
            self.entries[name]["on_object"] = round(fraction, 4)
        worst = agreement.worst_part()
        self.console.say(f"    agreement with the picture: silhouette IoU {agreement.silhouette_iou:.2f} (at least "
                         f"{MIN_SILHOUETTE_IOU:.2f} agrees); it explains {100 * agreement.edge_recall:.0f}% of the "
                         f"picture's edges (at least {100 * MIN_EDGE_RECALL:.0f}%); part {worst[0]!r} lies "
                         f"{100 * worst[1]:.0f}% on the object")
        if agrees:
            return
        if accepted:
            self.console.say("    the predicted assembly does not match the picture; building it anyway "
                             "(--accept-prediction)")
            return
        raise StageFailed(EXIT_DISAGREES, "repair",
                          f"the predicted assembly does not match the picture: {'; '.join(shortfalls)} (part "
                          f"{worst[0]!r} lies {100 * worst[1]:.0f}% on the object); overview.png shows both. Nothing "
                          "was planned: give the true poses with --poses, or build the prediction anyway with "
                          "--accept-prediction", worst[0])

    def _check_given_targets(self, assembly: Assembly) -> None:
        """Given targets put no part under the floor and no two parts into each other (:class:`BadTarget`)."""
        from planning.collision import ConvexPart, overlapping_pairs

        lowest = {p.name: float(p.assembly_from_part.apply(p.mesh.vertices)[:, 2].min()) for p in assembly.parts}
        name = min(lowest, key=lowest.get)
        if lowest[name] < -MAX_BELOW_FLOOR_M:
            raise BadTarget(f"{self.args.poses}: part {name!r} reaches {-lowest[name] * 1000:.0f} mm below the floor; "
                            "in the assembly frame the floor is z = 0 and the object stands on it, so check its pose "
                            "(or move every part up by that much)")
        convex = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
        pairs = overlapping_pairs(convex, [p.assembly_from_part for p in assembly.parts], MAX_FITTING_OVERLAP_M)
        if pairs:
            a, b, depth = pairs[0]
            more = f" ({len(pairs) - 1} more pair(s) too)" if len(pairs) > 1 else ""
            raise BadTarget(f"{self.args.poses}: parts {a!r} and {b!r} overlap by {depth * 1000:.0f} mm at their "
                            f"targets{more}, more than the {MAX_FITTING_OVERLAP_M * 1000:.0f} mm a connector's hole or "
                            "a model's slack accounts for; check their poses (one part placed at another's position, "
                            "or a wrong unit)")

    def _repair(self, assembly: Assembly) -> tuple[Assembly, tuple[str, str] | None]:
        """The repaired assembly, and (message, part) when two of its parts still cross (``None`` otherwise)."""
        from planning.collision import ConvexPart
        from planning.repair import RepairSettings, repair_poses

        if self.given is not None and not REPAIR_GIVEN_POSES:
            self.report["repair"] = {"applied": False, "reason": "poses given"}
            return assembly, None
        convex = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts]
        settings = RepairSettings()
        poses, repair = repair_poses(convex, [p.assembly_from_part for p in assembly.parts], settings)
        for name in assembly.part_names:
            self.entries[name]["repair"] = {"translation_m": repair.translation_m[name],
                                            "rotation_deg": repair.rotation_deg[name]}
        self.report["repair"] = {"applied": True,
                                 "deepest_penetration_before_m": repair.deepest_penetration_before_m,
                                 "deepest_penetration_after_m": repair.deepest_penetration_after_m,
                                 "overlapping_pairs_after": [{"parts": [a, b], "depth_m": depth}
                                                             for a, b, depth in repair.overlapping_pairs_after],
                                 "crossed_parts": list(repair.crossed_parts),
                                 "max_translation_m": settings.max_translation_m,
                                 "crossing_translation_m": settings.crossing_translation_m,
                                 "rest_distance_m": settings.rest_distance_m,
                                 "lowered_m": repair.lowered_m}
        if repair.crossed_parts:
            turned = "turned onto the assembly axes and " if settings.crossing_align_tolerance_deg >= 180 else ""
            self.console.say(f"    parts crossing another by over {settings.crossing_depth_m * 1000:.0f} mm, {turned}"
                             f"allowed to move up to "
                             f"{settings.crossing_translation_m * 1000:.0f} mm (the others "
                             f"{settings.max_translation_m * 1000:.0f} mm): {', '.join(repair.crossed_parts)}")
        if repair.lowered_m:
            self.console.say(f"    no part touched the floor after the repair: the whole assembly lowered "
                             f"{repair.lowered_m * 1000:.0f} mm onto it")
        crossed = crossing_failure(repair.overlapping_pairs_after, MAX_FITTING_OVERLAP_M,
                                   max(settings.max_translation_m, settings.crossing_translation_m))
        return assembly_with_poses(assembly, dict(zip(assembly.part_names, poses))), crossed

    # --- 3-7: sequence, kitting, motion, timing, simulation ---------------------------------------------------
    def _record_sequence(self, sequence) -> None:
        for index, step in enumerate(sequence.steps, start=1):
            entry = self.entries[step.part]
            entry.update(order=index, insertion_direction=[float(v) for v in step.insertion_direction],
                         fastened_to=list(step.fastened_to))

    def plan_and_simulate(self) -> int:
        """Sequence, kitting, motion and timing for the target standing on the jig; where no plan builds it
        standing (and the scene allows it, ``[fixture] upside_down``), for the target turned over
        (:func:`planning.fixture.upside_down`); then the limit check and the simulation."""
        from planning.fixture import upside_down

        try:
            self._plan_build(self.target, Pose([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]))
        except StageFailed as standing:
            if not self.scene.fixture.upside_down:
                raise
            self.console.say("    no plan builds it standing: " + indented(str(standing), "      ")
                             + "\n    building it upside down: turned over about its x axis on the jig, top first")
            turned, turned_from_target = upside_down(self.target)
            records = {name: dict(entry) for name, entry in self.entries.items()}
            try:
                self._plan_build(turned, turned_from_target)
            except StageFailed as exc:
                for name, entry in self.entries.items():  # the report keeps the standing build's order
                    entry.clear()
                    entry.update(records[name])
                raise StageFailed(exc.exit_code, standing.stage, f"{standing}\nbuilding it upside down failed too, "
                                  f"at {exc.stage}: {indented(str(exc), '  ')}", standing.part) from exc
        self._check_limits()
        return self._simulate()

    def _plan_build(self, build: Assembly, build_from_target: Pose) -> None:
        """Plan ``build`` (the target as the jig holds it: ``build_from_target`` is the target's assembly frame in
        the build's) or raise :class:`StageFailed` (exit 3)."""
        from cell.plan import DEFAULT_TIME_BUDGET_S, PlanningFailed, plan_cell
        from cell.task import LONGEST_WAY_IN_M
        from planning.motion import MotionSettings
        from planning.sequence import failure_summary, plan_assembly_sequence

        upside_down = not np.allclose(build_from_target.rotation, np.eye(3))
        how = "upside down, " if upside_down else ""
        with self.console.stage("sequence", f"{how}assembly by disassembly"):
            sequence = plan_assembly_sequence(build, seed=self.args.seed, max_overlap_exit_m=LONGEST_WAY_IN_M)
        if not sequence.success:
            self.report.setdefault("sequence_failures", []).append(
                {"upside_down": upside_down, "reason": sequence.reason, "blocking": dict(sequence.blocking),
                 "blocking_kind": dict(sequence.blocking_kind)})
            raise StageFailed(EXIT_PLANNING, "sequence", failure_summary(sequence))
        self._record_sequence(sequence)
        self.console.say("    order: " + " > ".join(sequence.order))

        bars = []

        def on_stage(name: str, jig_turn_deg: float, jig_slide_m: float) -> None:
            for bar in bars:
                bar.close()
            bars.clear()
            index = ("kitting", "motion").index(name) + 4
            detail = {"kitting": "stable poses on pedestals, a grasp valid at the pick and at the target",
                      "motion": "OMPL paths, straight approaches and insertions, Ruckig timing"}[name]
            turned = f"jig turned {jig_turn_deg:.0f} deg, " if jig_turn_deg else ""
            turned += f"jig slid {100 * jig_slide_m:.0f} cm toward the robot, " if jig_slide_m else ""
            self.console.say(f"[{index}/8] {name}: {how}{turned}{detail}")
            if name == "motion":
                bars.append(self.console.bar(len(build.parts), "part"))

        def progress(fraction: float) -> None:
            if bars:
                bars[0].n = round(fraction * bars[0].total)
                bars[0].refresh()

        def on_note(text: str) -> None:
            again = bool(bars)  # a grasp retry within the motion stage: its bar starts again
            for bar in bars:
                bar.close()
            bars.clear()
            self.console.say("\n".join(f"    {line}" for line in text.splitlines()))
            self.report.setdefault("planning_notes", []).append({"upside_down": upside_down, "note": text})
            if again:
                bars.append(self.console.bar(len(build.parts), "part"))

        self.report.setdefault("planning_notes", [])  # present, and empty, where the first try worked
        seconds = self.console.stage_seconds
        budget = {} if self.args.time_budget is None else {"time_budget_s": self.args.time_budget}
        self.report["time_budget_s"] = budget.get("time_budget_s", DEFAULT_TIME_BUDGET_S)
        # the planner's own work, counted against the budget (CPU seconds), for each build tried
        cpu_started = time.thread_time()
        spent = self.report.setdefault("planning_cpu_s", {})
        try:
            plan = plan_cell(self.scene, build, sequence, seed=self.args.seed,
                             motion=MotionSettings(planner=self.args.planner, seed=self.args.seed),
                             progress=progress, on_stage=on_stage, on_note=on_note,
                             density_kg_m3=self.density_kg_m3, part_density_kg_m3=self.part_density_kg_m3,
                             **budget)
        except PlanningFailed as exc:
            for name, value in exc.seconds.items():
                seconds[name] = seconds.get(name, 0.0) + value
            raise StageFailed(EXIT_PLANNING, exc.stage, str(exc), exc.part) from exc
        finally:
            for bar in bars:
                bar.close()
            spent["upside_down" if upside_down else "standing"] = time.thread_time() - cpu_started
        self.plan = plan
        for name in ("kitting", "motion", "timing"):
            seconds[name] = seconds.get(name, 0.0) + plan.seconds.get(name, 0.0)
        if plan.sequence is not None and plan.sequence.order != sequence.order:
            self._record_sequence(plan.sequence)
            self.console.say("    order planned again with the arm checked at every target: "
                             + " > ".join(plan.sequence.order))
        # the target's assembly frame in the world (turned over when it is built upside down)
        self.world_from_target = plan.world_from_assembly @ build_from_target
        self.report["world_from_assembly"] = pose_json(self.world_from_target)
        self.report["jig_turn_deg"] = plan.jig_turn_deg
        self.report["jig_slide_m"] = plan.jig_slide_m
        self.report["upside_down"] = upside_down
        if upside_down:
            self.report["world_from_build"] = pose_json(plan.world_from_assembly)
        for task in plan.tasks:
            self.entries[task.part]["target_world_from_part"] = pose_json(task.world_from_target)
        for planned in plan.task_plan.parts:
            self.entries[planned.part]["carry_check"] = planned.carry_check
        for slot in plan.slots:
            self.entries[slot.part]["kitting_world_from_part"] = pose_json(slot.world_from_part)
            self.entries[slot.part]["kitting_wedged"] = slot.wedged
            # on a board (its pedestal None), else on its own pedestal or posts
            self.entries[slot.part]["kitting_support"] = slot.rests_on or (
                "posts" if slot.pedestal.posts else "pedestal")
            if slot.wedged:
                from cell.resting import WEDGED_FORCE_RATIO

                self.console.say(f"    kit: {slot.part!r} rests in none of its poses unless wedged into its pedestal "
                                 f"or chocks (its contacts press it with over {WEDGED_FORCE_RATIO:g} times its "
                                 "weight), and lies so: the arm might not pull it out")
            self.entries[slot.part]["grasp"] = {"part_from_tcp": pose_json(slot.grasp.part_from_tcp),
                                                "width_m": slot.grasp.width_m, "opening_m": slot.grasp.opening_m,
                                                "pick_opening_m": slot.grasp.opening_at_pick_m}
        self.report["trajectory_duration_s"] = plan.program.duration_s
        built = " built upside down," if upside_down else ""
        self.console.say(f"[6/8] timing:{built} a {plan.program.duration_s:.1f} s robot program, within the "
                         f"{self.scene.robot.limits.description}'s published limits")

    def _check_limits(self) -> None:
        """The timed program within the arm's limits, on its own samples and as the controller plays its exported
        points (:func:`cell.program.check_controller_replay`), or :class:`StageFailed` (exit 3, stage "timing")."""
        from cell.program import CSV_RATE_HZ, LimitViolation, arm_limits, check_controller_replay, check_limits

        samples = self.plan.program.sample(CSV_RATE_HZ)
        lower, upper = self.plan.joint_limits
        try:
            check_limits(samples, lower, upper, arm_limits(self.plan.program.robot))
        except LimitViolation as exc:
            raise StageFailed(EXIT_PLANNING, "timing", f"the timed program breaks a limit: {exc}") from exc
        try:
            points = check_controller_replay(self.plan.program, samples, lower, upper)
        except LimitViolation as exc:
            raise StageFailed(EXIT_PLANNING, "timing", f"the exported program breaks a limit at {exc}") from exc
        self.samples, self.points = samples, points  # only a program within the limits is exported

    def _simulate(self) -> int:
        from cell.simulate import SimPart, SimSettings, StaticBody, simulate_program

        plan = self.plan
        fasten = {name: tuple(self.entries[name].get("fastened_to", ())) for name in self.target.part_names}
        parts = [SimPart(t.part, self.target.part(t.part).mesh, t.world_from_pick, t.world_from_target,
                         tuple("fixture" if n == "floor" else n for n in fasten[t.part]),
                         self.part_density_kg_m3[t.part])
                 for t in plan.tasks]
        static = [StaticBody(o.name, o.mesh, o.world_from_obstacle) for o in plan.static]
        settings = SimSettings(record_every_s=None if self.args.no_animation else ANIMATION_FRAME_S,
                               density_kg_m3=self.density_kg_m3, robot_model=self.scene.robot.model)
        with self.console.stage("simulation", f"PyBullet physics at {settings.rate_hz:.0f} Hz, "
                                              f"{plan.program.duration_s:.0f} s of robot motion"):
            bar = self.console.bar(100, "%")
            try:
                self.simulation = simulate_program(plan.program, parts, static, self.scene.robot.world_from_base,
                                                   settings, progress=lambda f: _advance(bar, f))
            finally:
                bar.close()
        result = self.simulation
        for part in result.parts:
            entry = self.entries[part.name]
            entry.update(final_world_from_part=pose_json(part.world_from_final),
                         position_error_m=part.position_error_m, rotation_error_deg=part.rotation_error_deg,
                         within_tolerance=part.within_tolerance)
        self.report["simulation"] = result.summary()
        if result.overlaps_at_target:
            a, b, depth = result.overlaps_at_target[0]
            self.console.say(f"    {len(result.overlaps_at_target)} pair(s) of parts overlap at their targets (deepest "
                             f"{depth * 1000:.1f} mm, {a} and {b}): simulated as fitting, without contact between them")
        if not result.success:
            raise StageFailed(EXIT_SIMULATION, "simulation", result.failure_words())
        return EXIT_OK

    # --- 8: files -------------------------------------------------------------------------------------------
    def write(self, folder) -> None:
        from PIL import Image

        from cell.program import write_exports
        from cell.report import overview_image

        if self.plan is not None and self.samples is not None:
            lower, upper = self.plan.joint_limits
            write_exports(self.plan.program, folder, lower, upper, self.samples, self.points,
                          self.args.bag_storage)
        if self.target is not None:
            final = None
            if self.simulation is not None:
                assembly_from_world = self.world_from_target.inverse()
                final = assembly_with_poses(self.target, {p.name: assembly_from_world @ p.world_from_final
                                                          for p in self.simulation.parts})
            caption = "target assembly (given)" if self.given is not None else "predicted assembly (repaired)"
            result = ("simulated result (built upside down, shown turned back)" if self.report.get("upside_down")
                      else "simulated result")
            agreement = None
            if self.agreement is not None:
                agreement = (self.agreement.overlay(self.image),
                             f"silhouette IoU {self.agreement.silhouette_iou:.2f}, edges "
                             f"{100 * self.agreement.edge_recall:.0f}%: green both, red prediction only, blue picture "
                             "only")
            picture = overview_image(self.image, self.target, final, seed=self.args.seed, target_caption=caption,
                                     result_caption=result, agreement=agreement)
            Image.fromarray(picture).save(folder / "overview.png")
        if self.simulation is not None and self.simulation.frames:
            from cell.simulate import write_gif

            write_gif(self.simulation.frames, folder / "animation.gif", fps=ANIMATION_FPS)


def _advance(bar, fraction: float) -> None:
    bar.n = round(100 * fraction)
    bar.refresh()
