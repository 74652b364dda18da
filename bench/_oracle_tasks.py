"""Tasks run inside bench/.oracles (see _oracles.py): `python _oracle_tasks.py TASK in.npz out.npz`.
Only the oracles' own libraries are used here, never splatwright."""

import statistics
import sys
import time

import numpy as np


def _median_time(fn, repeat):
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def pinocchio_fk(urdf, links, joint_names, joint_values, repeat):
    """Link frames from Pinocchio's forward kinematics (framesForwardKinematics), and its time for one
    configuration and for a Python loop over the batch."""
    import pinocchio as pin

    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    values = dict(zip(joint_names.tolist(), np.asarray(joint_values).T))
    q = np.zeros((len(joint_values), model.nq))
    for j in range(1, model.njoints):
        name = model.names[j]
        if model.joints[j].nq == 1:
            q[:, model.joints[j].idx_q] = values[name]
    frames = [model.getFrameId(str(name), pin.BODY) for name in links]
    out = np.empty((len(q), len(frames), 4, 4))
    for b, config in enumerate(q):
        pin.framesForwardKinematics(model, data, config)
        for k, f in enumerate(frames):
            out[b, k] = data.oMf[f].homogeneous
    one = q[0]
    single = _median_time(lambda: [pin.framesForwardKinematics(model, data, one) for _ in range(1000)], repeat) / 1000
    batch = _median_time(lambda: [pin.framesForwardKinematics(model, data, c) for c in q], repeat)
    return {"transforms": out, "single": single, "batch": batch, "nq": model.nq}


def fcl_distances(files, links, origins, scales, worlds, box_size, box_pose, repeat):
    """Per configuration: does any visual mesh of the robot (posed by `worlds`) hit the box, the least
    mesh-to-box distance (0 when they touch), and fcl's time for the collision test of all links."""
    import fcl
    import trimesh

    models = []
    for path, scale in zip(files.tolist(), scales):
        mesh = trimesh.load(path, force="mesh", process=False)
        model = fcl.BVHModel()
        model.beginModel(len(mesh.vertices), len(mesh.faces))
        model.addSubModel(np.asarray(mesh.vertices, np.float64) * scale, np.asarray(mesh.faces, np.int64))
        model.endModel()
        models.append(model)
    box = fcl.CollisionObject(fcl.Box(*box_size), fcl.Transform(box_pose[:3, :3], box_pose[:3, 3]))
    objects = [fcl.CollisionObject(m, fcl.Transform()) for m in models]
    hit = np.zeros(len(worlds), bool)
    distance = np.zeros(len(worlds))

    def place(world):
        for obj, link, origin in zip(objects, links, origins):
            m = world[link] @ origin
            obj.setTransform(fcl.Transform(m[:3, :3], m[:3, 3]))

    def collide():
        return any(fcl.collide(obj, box, fcl.CollisionRequest(), fcl.CollisionResult()) for obj in objects)

    times = []
    for c, world in enumerate(worlds):
        place(world)
        hit[c] = collide()
        times.append(_median_time(collide, repeat))
        if not hit[c]:
            distance[c] = min(fcl.distance(obj, box, fcl.DistanceRequest(), fcl.DistanceResult()) for obj in objects)
    return {"hit": hit, "distance": distance, "collide_time": np.array(times)}


TASKS = {"pinocchio_fk": pinocchio_fk, "fcl_distances": fcl_distances}


if __name__ == "__main__":
    task, src, dst = sys.argv[1:4]
    with np.load(src) as inputs:
        args = {k: (inputs[k].item() if inputs[k].ndim == 0 else inputs[k]) for k in inputs.files}
    np.savez(dst, **TASKS[task](**args))
