"""Evaluation on assembly folders rendered on the fly (``python -m perception.evaluate --assemblies DIR``).

Every assembly folder under ``DIR`` (procedural ones from ``python -m perception.synth`` or real furniture) is
rendered ``views`` times with the project's renderer (parts of more than 40,000 faces decimated for the picture
only: PyBullet's vertex limit) and :func:`cell.render.sample_camera` (assembly ``i`` in
sorted order draws from ``numpy.random.default_rng([seed, i])``; its parts come in a random order, as a
user's do: :func:`shuffled_parts`), run through the model exactly as
:func:`perception.predict.predict` runs it, and scored against the truth:

- the paper's figures (Part Accuracy, Shape Chamfer, PA of visible and invisible parts), in the network's frame
  (object-centred camera frame, normalised units; :mod:`perception.metrics`);
- connectivity: the fraction of parts touching at least one other part (:func:`planning.contact.contact_graph`
  in the predicted upright assembly frame), and the fraction of objects whose parts form one connected whole;
- the same after :func:`planning.repair.repair_poses` (mapped back to the network's frame for PA and SC), and
  the deepest penetration between two parts before and after it (metres); the views whose parts still cross
  after it (a pair overlapping by more than :data:`planning.collision.MAX_FITTING_OVERLAP_M`), how many of those
  pairs are equivalent parts (the network hedges between parts it cannot tell apart), and the Part Accuracy of
  those views and of the others;
- the up-axis error (degrees between the predicted and the true up direction, camera frame), the CPU time of
  inference per object (normalising the parts, the network, up and frames; not rendering or repair) and the
  process's peak resident memory.
"""

from __future__ import annotations

import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx
import numpy as np
from torch import nn
from tqdm import tqdm

from cell.render import Appearance, AssemblyRenderer, Rendering, sample_camera
from perception.agreement import object_mask, picture_agreement
from perception.elevation import image_elevation_deg
from perception.metrics import AssemblyResult, MetricSummary, evaluate_assembly
from perception.normalize import camera_from_canonical_norm
from perception.placement import Placement, place_parts
from perception.predict import PreparedParts, prepare_parts, run_network
from perception.solver import SolverSettings, solve
from perception.upright import angle_deg
from planning.assembly import ASSEMBLY_FILE, Assembly, AssemblyError, read_assembly
from planning.collision import MAX_FITTING_OVERLAP_M, ConvexPart
from planning.contact import FLOOR, all_grounded, contact_graph
from planning.pose import Pose
from planning.repair import RepairSettings, repair_poses

DEFAULT_REPAIR = RepairSettings()  # what cell.run applies to predicted poses


def assembly_folders(root: str | Path) -> list[Path]:
    """The assembly folders under ``root`` (its subfolders holding an ``assembly.json``, sorted by name), or
    ``root`` itself if it is one. Raises ``FileNotFoundError`` naming ``root`` when there is none."""
    root = Path(root)
    if (root / ASSEMBLY_FILE).is_file():
        return [root]
    if not root.is_dir():
        raise FileNotFoundError(f"assemblies folder {root} not found")
    folders = sorted(p for p in root.iterdir() if (p / ASSEMBLY_FILE).is_file())
    if not folders:
        raise FileNotFoundError(f"no assembly folders (subfolders with {ASSEMBLY_FILE}) in {root}")
    return folders


def truth_targets(view: Rendering, parts: PreparedParts, centre_camera_m: np.ndarray) -> tuple[np.ndarray, ...]:
    """The network's targets for one view: quat_wxyz (N, 4) and trans_norm (N, 3) of the canonical parts in the
    object-centred camera frame (normalised units)."""
    targets = [camera_from_canonical_norm(pose, canon, centre_camera_m, parts.normalized.scale_per_m)
               for pose, canon in zip(view.camera_from_part, parts.normalized.part_from_canonical_m)]
    return np.stack([q for q, _ in targets]), np.stack([t for _, t in targets])


def network_frame(camera_from_part: list[Pose], parts: PreparedParts,
                  centre_camera_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame poses (metres, mesh frames) back in the network's frame (quat (N, 4), trans_norm (N, 3))."""
    pairs = [camera_from_canonical_norm(pose, canon, centre_camera_m, parts.normalized.scale_per_m)
             for pose, canon in zip(camera_from_part, parts.normalized.part_from_canonical_m)]
    return np.stack([q for q, _ in pairs]), np.stack([t for _, t in pairs])


def connectivity(contacts: nx.Graph) -> tuple[float, bool]:
    """(fraction of parts touching another part, whether all parts form one connected whole) of a
    :func:`planning.contact.contact_graph`, floor excluded."""
    graph = contacts.subgraph(node for node in contacts if node != FLOOR)
    if graph.number_of_nodes() <= 1:
        return 1.0, True
    touching = sum(1 for node in graph if graph.degree(node) > 0)
    return touching / graph.number_of_nodes(), nx.is_connected(graph)


def grounded(contacts: nx.Graph) -> bool:
    """Whether every part of a :func:`planning.contact.contact_graph` has a path of contacts to the floor
    (:func:`planning.contact.all_grounded`), which a standing build needs."""
    return all_grounded(contacts, {node for node in contacts if node != FLOOR})




@dataclass
class ViewOutcome:
    """The figures of one rendered view of one object."""

    name: str
    parts: int
    before: AssemblyResult
    after: AssemblyResult | None
    connectivity: dict
    up_error_deg: float
    inference_s: float  # wall clock
    inference_cpu_s: float  # CPU time of this process (all its threads): the measure a busy machine disturbs least
    depth_error_m: float
    penetration_m: dict = field(default_factory=dict)  # deepest penetration between two parts: before, after repair
    deepest_overlap_after: dict | None = None  # after repair: {"parts": [a, b], "depth_m", "equivalent"}
    # the repaired and the true assembly drawn against the picture's object (perception.agreement): silhouette IoU
    agreement: dict = field(default_factory=dict)
    solved: AssemblyResult | None = None  # after the picture solver (perception.solver), before repair
    solved_repaired: AssemblyResult | None = None  # after the solver and the repair: what cell.run builds
    solver: dict = field(default_factory=dict)  # the solver's figures (score, IoU before and after, seconds)


@dataclass
class Accumulator:
    outcomes: list[ViewOutcome] = field(default_factory=list)

    def summary(self) -> dict:
        before, after = MetricSummary(), MetricSummary()
        for o in self.outcomes:
            before.add(o.before)
            if o.after is not None:
                after.add(o.after)
        figures = before.summary()
        figures["right_object_rate"] = right_object_rate([o.before for o in self.outcomes])
        up = np.array([o.up_error_deg for o in self.outcomes])
        seconds = np.array([o.inference_s for o in self.outcomes])

        def mean_of(key):
            values = [o.connectivity[key] for o in self.outcomes if key in o.connectivity]
            return float(np.mean(values)) if values else float("nan")

        figures["connectivity"] = {key: mean_of(key) for key in (
            "truth", "predicted", "repaired", "truth_connected", "predicted_connected", "repaired_connected",
            "truth_grounded", "predicted_grounded", "repaired_grounded")}
        if after.results:
            figures["after_repair"] = after.summary()
            figures["after_repair"]["right_object_rate"] = right_object_rate([o.after for o in self.outcomes
                                                                              if o.after is not None])
            figures["deepest_penetration_m"] = {
                key: _stats(np.array([o.penetration_m[key] for o in self.outcomes if o.penetration_m]))
                for key in ("before", "after")}
            repaired = [o for o in self.outcomes if o.after is not None]
            crosses = [o.deepest_overlap_after is not None
                       and o.deepest_overlap_after["depth_m"] > MAX_FITTING_OVERLAP_M for o in repaired]
            crossing = [o for o, c in zip(repaired, crosses) if c]
            other = [o for o, c in zip(repaired, crosses) if not c]

            def mean_part_accuracy(views):  # over views, before repair (nan for none)
                return float(np.mean([np.mean(o.before.correct) for o in views])) if views else float("nan")

            figures["crossing_after_repair"] = {
                "threshold_m": MAX_FITTING_OVERLAP_M, "views": len(crossing) / max(len(repaired), 1),
                "deepest_pair_equivalent": float(np.mean([o.deepest_overlap_after["equivalent"] for o in crossing]))
                if crossing else float("nan"),
                "part_accuracy_crossing": mean_part_accuracy(crossing),
                "part_accuracy_other": mean_part_accuracy(other)}
        solved = [o for o in self.outcomes if o.solved_repaired is not None]
        if solved:
            figures["after_solver"] = _solver_figures(solved)
        figures["up_error_deg"] = _stats(up) | {"within_5_deg": float(np.mean(up <= 5.0)) if len(up) else float("nan")}
        figures["depth_error_m"] = _stats(np.array([o.depth_error_m for o in self.outcomes]))
        figures["inference_s"] = _stats(seconds)
        figures["inference_cpu_s"] = _stats(np.array([o.inference_cpu_s for o in self.outcomes]))
        figures["peak_memory_mb"] = peak_memory_mb()
        return figures


def right_object_rate(results: list[AssemblyResult]) -> float:
    """The fraction of objects whose every part passes Part Accuracy (what a robot cell needs)."""
    return float(np.mean([np.all(r.correct) for r in results])) if results else float("nan")


def _solver_figures(outcomes: list[ViewOutcome]) -> dict:
    """The ablation over the views the solver ran on: network, + repair, + solver, + solver and repair."""
    stages = {"network": [o.before for o in outcomes], "repair": [o.after for o in outcomes],
              "solver": [o.solved for o in outcomes], "solver_repair": [o.solved_repaired for o in outcomes]}
    figures = {name: {"part_accuracy": float(np.mean(np.concatenate([r.correct for r in results]))),
                      "right_object_rate": right_object_rate(results)} for name, results in stages.items()}
    return {**figures["solver_repair"], "stages": figures, "views": len(outcomes),
            "seconds": _stats(np.array([o.solver["seconds"] for o in outcomes]))}


def peak_memory_mb() -> float:
    """This process's peak resident memory in MB: ``VmHWM`` of ``/proc/self/status`` where there is one. Not
    ``getrusage``'s ``ru_maxrss`` there: Linux carries the peak of the image a process was forked from across
    ``exec``, so a small process started by a large one reported the large one's peak (2,870 MB and 1,701 MB for
    ``predict`` runs that peak at 420 MB)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _stats(values: np.ndarray) -> dict:
    if len(values) == 0:
        return {"mean": float("nan"), "median": float("nan"), "p95": float("nan"), "max": float("nan")}
    return {"mean": float(np.mean(values)), "median": float(np.median(values)),
            "p95": float(np.percentile(values, 95)), "max": float(np.max(values))}


def evaluate_view(model: nn.Module, view: Rendering, assembly: Assembly, parts: PreparedParts,
                  convex: list[ConvexPart] | None, prepare_s: tuple[float, float], max_parts: int,
                  name: str, repair_settings: RepairSettings = DEFAULT_REPAIR,
                  solver: SolverSettings | None = None) -> ViewOutcome:
    """Predict one rendered view and score it (``convex``: the parts' convex pieces for connectivity and repair;
    ``None`` skips both). ``prepare_s``: (wall, CPU) seconds :func:`prepare_parts` took, counted as inference.
    ``solver``: also fit the prediction to the picture (:func:`perception.solver.solve`) and score it, before and
    after the repair."""
    bounds = assembly.bounds()
    centre_camera_m = view.camera_from_assembly.apply(0.5 * (bounds[0] + bounds[1]))
    gt_quat, gt_trans = truth_targets(view, parts, centre_camera_m)
    start, start_cpu = time.perf_counter(), time.process_time()
    quat, trans, foreground = run_network(model, view.rgb, parts, max_parts, with_foreground=True)
    elevation = image_elevation_deg(view.rgb)  # as perception.predict reads up (None without its weights)
    placement: Placement = place_parts(quat, trans, parts.normalized, parts.meshes,
                                       image_elevation_deg=elevation)
    inference_s = prepare_s[0] + time.perf_counter() - start
    inference_cpu_s = prepare_s[1] + time.process_time() - start_cpu
    points, classes = parts.normalized.points_norm, parts.classes
    before = evaluate_assembly(points, quat, trans, gt_quat, gt_trans, classes, view.visible_pixels)
    up_true = view.camera_from_assembly.rotation[:, 2]
    outcome = ViewOutcome(name, len(parts.meshes), before, None, {}, angle_deg(placement.up.up_camera, up_true),
                          inference_s, inference_cpu_s, float(abs(placement.centre_camera_m[2] - centre_camera_m[2])))
    if convex is None:
        return outcome
    truth_poses = [p.assembly_from_part for p in assembly.parts]
    repaired, report = repair_poses(convex, placement.assembly_from_part, repair_settings)
    outcome.penetration_m = {"before": report.deepest_penetration_before_m, "after": report.deepest_penetration_after_m}
    if report.overlapping_pairs_after:
        a, b, depth = report.overlapping_pairs_after[0]
        index = {part.name: k for k, part in enumerate(convex)}
        outcome.deepest_overlap_after = {"parts": [a, b], "depth_m": depth,
                                         "equivalent": bool(parts.classes[index[a]] == parts.classes[index[b]])}
    camera_from_repaired = [placement.camera_from_assembly @ p for p in repaired]
    quat_r, trans_r = network_frame(camera_from_repaired, parts, placement.centre_camera_m)
    outcome.after = evaluate_assembly(points, quat_r, trans_r, gt_quat, gt_trans, classes, view.visible_pixels)
    mask, _ = object_mask(view.rgb, foreground)
    if solver is not None and mask.any():
        _solve_view(outcome, view, parts, convex, placement, mask, solver, repair_settings,
                    (points, gt_quat, gt_trans, classes))
    if mask.any():
        names = [p.name for p in convex]
        repaired_view = picture_agreement(mask, names, parts.meshes, camera_from_repaired, image=view.rgb)
        truth_view = picture_agreement(mask, names, parts.meshes,
                                       [view.camera_from_assembly @ p for p in truth_poses], image=view.rgb)
        outcome.agreement = {"repaired_iou": repaired_view.silhouette_iou,
                             "repaired_min_on_object": min(repaired_view.on_object.values()),
                             "truth_iou": truth_view.silhouette_iou,
                             "truth_min_on_object": min(truth_view.on_object.values()),
                             "object_fraction": repaired_view.object_fraction,
                             "repaired_edge_recall": repaired_view.edge_recall,
                             "truth_edge_recall": truth_view.edge_recall}
    for key, poses in (("truth", truth_poses), ("predicted", placement.assembly_from_part), ("repaired", repaired)):
        contacts = contact_graph(convex, poses)
        fraction, whole = connectivity(contacts)
        outcome.connectivity[key] = fraction
        outcome.connectivity[f"{key}_connected"] = float(whole)
        outcome.connectivity[f"{key}_grounded"] = float(grounded(contacts))
    return outcome


def _solve_view(outcome: ViewOutcome, view: Rendering, parts: PreparedParts, convex: list[ConvexPart],
                placement: Placement, mask: np.ndarray, settings: SolverSettings, repair_settings: RepairSettings,
                truth: tuple) -> None:
    """The solver's figures for one view, into ``outcome``: Part Accuracy after the solver, and after the solver
    and the repair."""
    points, gt_quat, gt_trans, classes = truth
    result = solve([c.piece_vertices for c in convex], parts.classes, placement.assembly_from_part,
                   placement.camera_from_assembly, mask, settings)
    outcome.solver = result.to_dict([c.name for c in convex])
    for attribute, poses in (("solved", result.assembly_from_part),
                             ("solved_repaired", repair_poses(convex, result.assembly_from_part, repair_settings)[0])):
        quat, trans = network_frame([placement.camera_from_assembly @ p for p in poses], parts,
                                    placement.centre_camera_m)
        setattr(outcome, attribute, evaluate_assembly(points, quat, trans, gt_quat, gt_trans, classes,
                                                      view.visible_pixels))


def shuffled_parts(assembly: Assembly, seed: int, index: int) -> Assembly:
    """``assembly`` with its parts in a random order from ``numpy.random.default_rng([seed, index, 1])``
    (assembly ``index`` in sorted order): the network meets them unordered, as a user's parts come."""
    order = np.random.default_rng([seed, index, 1]).permutation(len(assembly.parts))
    return Assembly(assembly.name, [assembly.parts[k] for k in order], assembly.metadata)


def evaluate_assemblies(model: nn.Module, root: str | Path, views: int = 1, seed: int = 0, repair: bool = True,
                        max_parts: int = 20, limit: int = 0, progress: bool = False,
                        repair_settings: RepairSettings = DEFAULT_REPAIR, shuffle_parts: bool = True,
                        solver: SolverSettings | None = None, materials: str = "parts") -> dict:
    """Figures over every assembly folder under ``root`` (see the module docstring); ``limit``: the first N
    folders only (0: all). ``shuffle_parts``: the parts in a random order (:func:`shuffled_parts`), not the
    order of the folder's ``assembly.json`` (procedural generators list them in a fixed order). ``solver``: also
    fit each prediction to its picture (:mod:`perception.solver`; figures under ``after_solver``). ``materials``:
    how the parts are coloured in the pictures (:data:`cell.render.MATERIALS`); the same views in every mode.
    Adds ``objects`` (those evaluated), ``unreadable`` (folder name and why, for folders that cannot be read: the
    others are still evaluated) and ``per_object`` (name, parts, PA, up error, inference time)."""
    folders = assembly_folders(root)
    if limit:
        folders = folders[:limit]
    accumulator = Accumulator()
    bar = tqdm(total=len(folders) * views, unit="view", disable=not progress, desc="evaluate")
    unreadable = []  # (folder name, why): an object that cannot be read is reported, and the rest evaluated
    for index, folder in enumerate(folders):
        try:
            assembly = read_assembly(folder)
        except AssemblyError as exc:
            unreadable.append({"name": folder.name, "error": str(exc)})
            bar.update(views)
            continue
        if shuffle_parts:
            assembly = shuffled_parts(assembly, seed, index)
        meshes = [p.mesh for p in assembly.parts]
        start, start_cpu = time.perf_counter(), time.process_time()
        parts = prepare_parts(meshes)
        prepare_s = (time.perf_counter() - start, time.process_time() - start_cpu)
        convex = [ConvexPart.from_mesh(p.name, p.mesh) for p in assembly.parts] if repair else None
        rng = np.random.default_rng([seed, index])
        with AssemblyRenderer(assembly) as renderer:
            for k in range(views):
                camera = sample_camera(rng, assembly.bounds())  # the camera is drawn before the colours
                view = renderer.render(camera, Appearance.sample(rng, len(meshes), materials))
                accumulator.outcomes.append(evaluate_view(model, view, assembly, parts, convex, prepare_s, max_parts,
                                                          f"{folder.name}/view{k}", repair_settings, solver))
                bar.update()
    bar.close()
    figures = accumulator.summary()
    figures["objects"] = len(folders) - len(unreadable)
    figures["unreadable"] = unreadable
    figures["per_object"] = [
        {"name": o.name, "parts": o.parts, "part_accuracy": float(np.mean(o.before.correct)),
         "part_accuracy_repaired": float(np.mean(o.after.correct)) if o.after is not None else None,
         "up_error_deg": round(o.up_error_deg, 3), "inference_s": round(o.inference_s, 4),
         "inference_cpu_s": round(o.inference_cpu_s, 4), "deepest_overlap_after": o.deepest_overlap_after,
         "picture_agreement": o.agreement, **o.connectivity,
         **({"part_accuracy_solved": float(np.mean(o.solved_repaired.correct)),
             "part_accuracy_solved_before_repair": float(np.mean(o.solved.correct)), "solver": o.solver}
            if o.solved_repaired is not None else {})}
        for o in accumulator.outcomes]
    return figures
