#!/usr/bin/python3
"""Fault campaign: every procedure, with the nodes it depends on killed (SIGKILL) at
seeded random times, and stray goals, non-finite poses and requests and stale parameters sent
to the running nodes. Each run is a real roslaunch on its own master (loopback); a probe node on
that master records the devices' last states and the afterloader's published journal.

Keys (reports/faults/summary.json): runs, hangs (no procedure exit within 30 s of the fault),
reports_naming_cause (fraction of kill runs whose report names the killed node), max_detect_s
(kill -> the procedure's supervisor saw it), unsafe_device_states (a live robot left moving or a
live afterloader's source left out when the procedure ended), lost_journal_entries (journal lines
an afterloader published that are not in its file, plus malformed robot journal lines),
refused_bad_inputs_fraction (bad inputs refused with state unchanged / bad inputs sent).

Usage: scripts/bench faults [--quick] [--seed N]  (run by scripts/bench; writes --out DIR)
"""
import argparse
import csv
import glob
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import time
import xmlrpc.client

HANG_S = 30.0  # a procedure that has not exited this long after the fault hangs

# procedure -> launch file, launch arguments, nodes it depends on, the log line that says the
# procedure is under way (kills happen after it), seconds of activity to draw the kill time from
PROCEDURES = {
    "hdr_delivery": dict(
        launch="hdr_delivery.launch",
        args=["synthetic_seed:=1", "time_scale:=20"],
        nodes=["afterloader", "dwell_scheduler"],
        running=r"hdr_procedure: dwell 1/", window=(0.2, 6.0)),
    "hdr_delivery_respawn": dict(
        launch="hdr_delivery.launch",
        args=["synthetic_seed:=2", "time_scale:=20", "respawn:=true"],
        nodes=["afterloader"],
        running=r"hdr_procedure: dwell 1/", window=(0.2, 5.0), resumes=True),
    "steerable_needle": dict(
        launch="steerable_needle.launch",
        args=["trials:=30", "time_scale:=20"],
        nodes=["steering_policy", "insertion_robot"],
        running=r"steerable_procedure: trial 1/", window=(0.1, 6.0)),
    "steerable_needle_image": dict(
        launch="steerable_needle.launch",
        args=["trials:=30", "time_scale:=20", "tracking:=image", "modality:=ultrasound"],
        nodes=["steering_policy", "insertion_robot", "imager", "tip_tracker"],
        running=r"steerable_procedure: trial 1/", window=(0.1, 6.0)),
    "steerable_needle_3d": dict(
        launch="steerable_needle_3d.launch",
        args=["trials:=30"],
        nodes=["steering_planner_3d", "insertion_robot"],
        running=r"steerable_procedure_3d: trial 1/", window=(0.5, 6.0), retracts=True),
    "rigid_seed_implant": dict(
        launch="rigid_seed_implant.launch",
        args=["insertion_velocity_m_s:=0.02", "retract_velocity_m_s:=0.05"],
        nodes=["tissue_sim", "rigid_planner", "insertion_robot"],
        running=r"insertion_procedure: target 1/", window=(0.1, 6.0)),
    "robot_procedure": dict(
        launch="robot_procedure.launch",
        args=["insertion_velocity_m_s:=0.02", "retract_velocity_m_s:=0.05"],
        nodes=["tissue_sim", "insertion_robot"],
        running=r"insertion_procedure: target 1/", window=(0.1, 6.0)),
    "registration": dict(
        launch="registration.launch",
        args=["cases_per_probe:=5"],
        nodes=["registration"],
        running=r"registration_procedure: balloon case 1", window=(0.02, 1.0)),
}


def free_port(rng):
    return 12000 + rng.randrange(3000)


class Run:
    """One roslaunch of a procedure (hold:=true, so the devices outlive the procedure and their
    final state can be read) with a probe node on the same master."""

    def __init__(self, out_dir, name, spec, port, extra_args=()):
        self.dir = os.path.join(out_dir, "runs", name)
        shutil.rmtree(self.dir, ignore_errors=True)  # a report left by an earlier bench is not this run's
        os.makedirs(self.dir)
        open(os.path.join(self.dir, ".needle_guidance_report"), "w").close()
        self.report_dir = self.dir
        self.port = port
        self.master = f"http://localhost:{port}"
        self.env = dict(os.environ, ROS_MASTER_URI=self.master, ROS_IP="127.0.0.1",
                        ROS_HOSTNAME="localhost", ROSCONSOLE_STDOUT_LINE_BUFFERED="1",
                        PYTHONUNBUFFERED="1")
        self.journal_dir = os.path.join(self.dir, "journal")
        self.robot_journal = os.path.join(self.dir, "robot_journal.csv")
        args = ["roslaunch", "-p", str(port), "--screen", "needle_guidance", spec["launch"],
                "rviz:=false"] + spec["args"]
        if spec["launch"] not in ("insertion_robot.launch", "steering_policy.launch"):
            args += [f"report_dir:={self.report_dir}", "hold:=true"]
        if spec["launch"].startswith("hdr"):
            args.append(f"journal_dir:={self.journal_dir}")
        planar = "3d" not in spec["launch"]
        if spec["launch"].startswith("steerable") or spec["launch"].startswith("insertion_robot"):
            args += [f"journal_file:={self.robot_journal}"]
        if spec["launch"].startswith("steer") and planar:
            args += [f"table_dir:={os.path.join(self.dir, 'tables')}"]
        args += list(extra_args)
        self.log_path = os.path.join(self.dir, "roslaunch.log")
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(args, stdout=self.log, stderr=subprocess.STDOUT, env=self.env,
                                     start_new_session=True)
        self.probe = None
        self.probe_out = os.path.join(self.dir, "probe.json")

    def start_probe(self):
        self.probe = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--probe",
                                       self.probe_out], env=self.env, start_new_session=True,
                                      stdout=open(os.path.join(self.dir, "probe.log"), "w"),
                                      stderr=subprocess.STDOUT)

    def stop_probe(self):
        if self.probe and self.probe.poll() is None:
            self.probe.send_signal(signal.SIGINT)
            try:
                self.probe.wait(10)
            except subprocess.TimeoutExpired:
                self.probe.kill()
        try:
            with open(self.probe_out) as f:
                return json.load(f)
        except (OSError, ValueError):
            return {}

    def log_text(self):
        with open(self.log_path, errors="replace") as f:
            return f.read()

    def wait_for_log(self, pattern, timeout_s):
        import re
        deadline = time.time() + timeout_s
        rx = re.compile(pattern)
        while time.time() < deadline:
            if rx.search(self.log_text()):
                return True
            if self.proc.poll() is not None:
                return False
            time.sleep(0.1)
        return False

    def node_pid(self, node):
        """The pid of /node from its own XML-RPC server, or None."""
        try:
            master = xmlrpc.client.ServerProxy(self.master)
            code, _, uri = master.lookupNode("/fault_campaign", "/" + node)
            if code != 1:
                return None
            code, _, pid = xmlrpc.client.ServerProxy(uri).getPid("/fault_campaign")
            return pid if code == 1 else None
        except (OSError, xmlrpc.client.Error):
            return None

    def node_alive(self, node):
        return self.node_pid(node) is not None

    def shutdown(self):
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self.log.close()


def procedure_node(spec):
    return {"hdr_delivery.launch": "hdr_procedure", "steerable_needle.launch": "steerable_procedure",
            "steerable_needle_3d.launch": "steerable_procedure_3d",
            "rigid_seed_implant.launch": "insertion_procedure",
            "robot_procedure.launch": "insertion_procedure",
            "registration.launch": "registration_procedure"}[spec["launch"]]


def read_summary(run):
    try:
        with open(os.path.join(run.report_dir, "summary.json")) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def journal_losses(run, probe):
    """Published afterloader journal lines missing from its files, plus malformed robot
    journal lines."""
    lost = 0
    published = probe.get("afterloader_journal", [])
    if published:
        lines = set()
        for path in glob.glob(os.path.join(run.journal_dir, "*.journal")):
            with open(path, errors="replace") as f:
                lines.update(line.rstrip("\n") for line in f)
        lost += sum(1 for line in published if line.rstrip("\n") not in lines)
    if os.path.exists(run.robot_journal):
        with open(run.robot_journal, errors="replace") as f:
            rows = list(csv.reader(f))
        if rows:
            width = len(rows[0])
            lost += sum(1 for r in rows[1:] if len(r) != width)
    return lost


def unsafe_states(probe, killed, spec):
    """A live device left in an unsafe state when the procedure had ended (for procedures that
    promise it, spec retracts: a live robot's needle left in the tissue)."""
    unsafe = []
    robot = probe.get("robot_state")
    if robot and killed != "insertion_robot" and robot.get("alive") and robot.get("is_busy"):
        unsafe.append("robot left moving (" + robot.get("active_joint", "") + ")")
    inserted = probe.get("robot_insertion_m")
    if spec.get("retracts") and robot and killed != "insertion_robot" and robot.get("alive") \
            and inserted is not None and inserted > 1e-6:
        unsafe.append(f"needle left in the tissue ({inserted * 1e3:.1f} mm inserted)")
    source = probe.get("afterloader_state")
    if source and killed != "afterloader" and source.get("alive") and source.get("source_in_patient"):
        unsafe.append("afterloader source left in the patient")
    return unsafe


def kill_run(out_dir, name, spec, node, rng, index):
    run = Run(out_dir, f"{index:02d}_{name}_{node}", spec, free_port(rng))
    rec = dict(run=index, procedure=name, fault="kill", node=node, hang=0, named=0,
               detect_s=float("nan"), unsafe="", lost=0, exit_s=float("nan"), outcome="")
    try:
        run.start_probe()
        if not run.wait_for_log(spec["running"], 120.0):
            rec["outcome"] = "procedure never started"
            rec["hang"] = 1
            return rec
        delay = rng.uniform(*spec["window"])
        time.sleep(delay)
        proc_node = procedure_node(spec)
        pid = run.node_pid(node)
        if read_summary(run) is not None or not run.node_alive(proc_node):
            rec["outcome"] = "the procedure had already ended at the kill time"
            rec["skipped"] = 1
            return rec
        if pid is None:
            rec["outcome"] = f"/{node} not running at the kill time (procedure already over?)"
            rec["skipped"] = 1
            return rec
        os.kill(pid, signal.SIGKILL)
        t_kill = time.time()
        rec["kill_after_running_s"] = round(delay, 3)
        # The procedure must end (or, with respawn, finish the delivery) within HANG_S.
        limit = HANG_S * (4 if spec.get("resumes") else 1)
        while time.time() - t_kill < limit:
            if read_summary(run) is not None and not run.node_alive(proc_node):
                break
            time.sleep(0.1)
        summary = read_summary(run)
        exited = not run.node_alive(proc_node)
        rec["exit_s"] = round(time.time() - t_kill, 2)
        if summary is None or not exited:
            rec["hang"] = 1
            rec["outcome"] = "no report" if summary is None else "procedure did not exit"
        else:
            text = json.dumps(summary)
            if spec.get("resumes"):
                rec["named"] = int(summary.get("success") is True and
                                   summary.get("afterloader_restarts", 0) >= 1)
                rec["outcome"] = f"resumed: success={summary.get('success')}"
            else:
                rec["named"] = int(summary.get("dead_node", "").strip("/") == node or
                                   f"/{node} " in text)
                rec["outcome"] = summary.get("status", "") + ": " + summary.get("cause", "")[:120]
            if summary.get("detected_unix_s", 0) > 0:
                rec["detect_s"] = round(summary["detected_unix_s"] - t_kill, 3)
        time.sleep(0.5)  # the devices' last states after the procedure ended
    finally:
        probe = run.stop_probe()
        run.shutdown()
    rec["unsafe"] = "; ".join(unsafe_states(probe, node, spec))
    rec["lost"] = journal_losses(run, probe)
    return rec


# ---- bad inputs (sent by the probe process, on a master with the nodes running) -----------

# Bad-input runs: a launch with the nodes idle (so that a refusal is for the bad value, not
# because a device is busy), its ready line, and the cases the sender tries on it.
BAD_INPUT_RUNS = [
    dict(name="robot", launch="insertion_robot.launch",
         args=["scene:=steering_workspace", "mode:=steerable"], ready=r"insertion_robot: ready",
         cases=["second_insert_goal", "insert_nan_target", "insert_inf_velocity", "height_nan",
                "flip_nan_velocity", "entry_pose_nan", "entry_pose_bad_bevel"]),
    dict(name="policy", launch="steering_policy.launch",
         args=["tip_topic:=/insertion_robot/measured_tip"], ready=r"steering_policy: ready",
         cases=["policy_nan_tip", "policy_inf_tip", "policy_nan_theta"]),
    dict(name="hdr", launch="hdr_delivery.launch", args=["synthetic_seed:=1", "time_scale:=50"],
         ready=r"hdr_procedure: dwell 1/",
         cases=["plan_dwells_bad_method", "plan_dwells_bad_id", "evaluate_nan",
                "deliver_nan_time"]),
    dict(name="rigid", launch="rigid_seed_implant.launch", args=["max_targets:=1"],
         ready=r"insertion_procedure: target 1/", cases=["plan_rigid_nan", "plan_rigid_outside"]),
]


def bad_input_run(out_dir, rng, index, spec):
    run = Run(out_dir, f"{index:02d}_bad_inputs_{spec['name']}", spec, free_port(rng))
    results = []
    try:
        run.wait_for_log(spec["ready"], 120.0)
        out = os.path.join(run.dir, "bad_inputs.json")
        subprocess.run([sys.executable, os.path.abspath(__file__), "--send-bad", out] +
                       spec["cases"], env=run.env, timeout=300,
                       stdout=open(os.path.join(run.dir, "send.log"), "w"),
                       stderr=subprocess.STDOUT)
        with open(out) as f:
            results = json.load(f)
    except (OSError, ValueError, subprocess.TimeoutExpired) as e:
        results = [dict(case=c, refused=0, detail=f"sender failed: {e}") for c in spec["cases"]]
    finally:
        run.shutdown()
    return results


def stale_parameter_run(out_dir, rng, index):
    """A parameter left on the master by an earlier launch must not reach a node that clears
    its parameters: the robot's ~scene set to a bogus value before the launch."""
    port = free_port(rng)
    env = dict(os.environ, ROS_MASTER_URI=f"http://localhost:{port}")
    core = subprocess.Popen(["roscore", "-p", str(port)], env=env, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        for _ in range(100):
            try:
                xmlrpc.client.ServerProxy(env["ROS_MASTER_URI"]).getSystemState("/x")
                break
            except OSError:
                time.sleep(0.1)
        master = xmlrpc.client.ServerProxy(env["ROS_MASTER_URI"])
        master.setParam("/stale", "/insertion_robot/stale_unknown_parameter", 42)
        master.setParam("/stale", "/insertion_procedure/planner", "no_such_planner")
        spec = PROCEDURES["robot_procedure"]
        run = Run(out_dir, f"{index:02d}_stale_parameters", spec, port,
                  extra_args=["max_targets:=1"])
        try:
            deadline = time.time() + 120
            while time.time() < deadline and read_summary(run) is None:
                time.sleep(0.2)
            has_stale = True
            try:
                code, _, _ = master.getParam("/x", "/insertion_procedure/planner")
                has_stale = code == 1
            except OSError:
                pass
            s = read_summary(run)
            ok = s is not None and not has_stale
            return dict(case="stale parameters on a shared master", refused=int(ok),
                        detail=f"report written: {s is not None}; stale ~planner left: {has_stale}")
        finally:
            run.shutdown()
    finally:
        os.killpg(core.pid, signal.SIGINT)
        core.wait(30)


# ---- probe and sender (separate processes: rospy on the run's master) ----------------------

def probe_main(out_path):
    import rospy
    from std_msgs.msg import String
    from needle_guidance.msg import AfterloaderState, OperatingState
    rospy.init_node("fault_probe", anonymous=True, disable_signals=True)
    data = {"afterloader_journal": []}

    def on_journal(msg):
        data["afterloader_journal"].append(msg.data)

    def on_state(msg):
        data["afterloader_state"] = dict(state=msg.state, source_in_patient=msg.source_in_patient,
                                         channel=msg.channel, alive=True, t=time.time())

    def on_robot(msg):
        data["robot_state"] = dict(state=msg.state, is_busy=msg.is_busy,
                                   active_joint=msg.active_joint, alive=True, t=time.time())

    rospy.Subscriber("/afterloader/journal", String, on_journal, queue_size=100000)
    rospy.Subscriber("/afterloader/state", AfterloaderState, on_state, queue_size=10)
    rospy.Subscriber("/insertion_robot/operating_state", OperatingState, on_robot, queue_size=10)

    def on_joints(msg):
        if "insertion" in msg.name:
            data["robot_insertion_m"] = msg.position[msg.name.index("insertion")]

    from sensor_msgs.msg import JointState
    rospy.Subscriber("/insertion_robot/measured_js", JointState, on_joints, queue_size=10)
    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    while not stop:
        time.sleep(0.05)
    master = xmlrpc.client.ServerProxy(os.environ["ROS_MASTER_URI"])
    for key, node in (("afterloader_state", "/afterloader"), ("robot_state", "/insertion_robot")):
        if key in data:
            try:
                code, _, uri = master.lookupNode("/fault_probe", node)
                data[key]["alive"] = code == 1 and xmlrpc.client.ServerProxy(uri).getPid("/p")[0] == 1
            except (OSError, xmlrpc.client.Error):
                data[key]["alive"] = False
    with open(out_path, "w") as f:
        json.dump(data, f)


def send_bad_main(out_path, cases):
    import actionlib
    import rospy
    from geometry_msgs.msg import Point, Pose2D
    from needle_guidance.msg import (LinearMoveAction, LinearMoveGoal, NeedleTip, SteeringControl,
                                     DeliverAction, DeliverGoal, DwellChannel, FlipBevelAction,
                                     FlipBevelGoal, AfterloaderState)
    from needle_guidance.srv import (PlanDwells, PlanRigid, SetEntryPose, EvaluateDelivery,
                                     PlanDwellsRequest, PlanRigidRequest, SetEntryPoseRequest,
                                     EvaluateDeliveryRequest)
    rospy.init_node("bad_input_sender", anonymous=True)
    results = []

    def record(case, refused, detail, expect=None):
        """Refused, and (with `expect`) for the bad value: the reason names one of the words."""
        detail = str(detail)
        if expect and not any(w in detail.lower() for w in expect):
            refused = False
            detail = "refused for another reason: " + detail
        results.append(dict(case=case, refused=int(bool(refused)), detail=detail[:240]))

    def goal_refused(client):
        r = client.get_result()
        return (client.get_state() in (actionlib.GoalStatus.REJECTED, actionlib.GoalStatus.ABORTED)
                or (r is not None and hasattr(r, "success") and not r.success)), \
            f"state {client.get_state()}: {client.get_goal_status_text()} " + \
            (getattr(r, "message", "") if r is not None else "")

    def call(name, srv, req):
        rospy.wait_for_service(name, 60)
        return rospy.ServiceProxy(name, srv)(req)

    def policy_answer(pose):
        got = []
        sub = rospy.Subscriber("/steering_policy/control", SteeringControl, got.append)
        pub = rospy.Publisher("/insertion_robot/measured_tip", NeedleTip, queue_size=1)
        time.sleep(1.0)
        tip = NeedleTip(pose=pose, bevel="left", source="fault_campaign")
        tip.header.stamp = rospy.Time.now()
        deadline = time.time() + 5
        while time.time() < deadline and not any(c.tip_source == "fault_campaign" for c in got):
            pub.publish(tip)
            time.sleep(0.2)
        sub.unregister()
        mine = [c for c in got if c.tip_source == "fault_campaign"]
        return mine[-1] if mine else None

    for case in cases:
        try:
            if case == "second_insert_goal":
                a = actionlib.SimpleActionClient("/insertion_robot/insert", LinearMoveAction)
                b = actionlib.SimpleActionClient("/insertion_robot/insert", LinearMoveAction)
                a.wait_for_server(rospy.Duration(30))
                b.wait_for_server(rospy.Duration(30))
                a.send_goal(LinearMoveGoal(target_m=0.02, velocity_m_s=0.002))
                time.sleep(0.5)
                b.send_goal(LinearMoveGoal(target_m=0.01, velocity_m_s=0.002))
                b.wait_for_result(rospy.Duration(5))
                first_running = a.get_state() == actionlib.GoalStatus.ACTIVE
                refused, detail = goal_refused(b)
                record(case, refused and first_running and
                       b.get_state() == actionlib.GoalStatus.REJECTED,
                       f"{detail}; the first goal still running: {first_running}")
                a.cancel_goal()
                a.wait_for_result(rospy.Duration(10))
                retract = actionlib.SimpleActionClient("/insertion_robot/retract", LinearMoveAction)
                retract.wait_for_server(rospy.Duration(10))
                retract.send_goal(LinearMoveGoal(target_m=0.0, velocity_m_s=0.01))
                retract.wait_for_result(rospy.Duration(20))
            elif case in ("insert_nan_target", "insert_inf_velocity", "height_nan"):
                action = "/insertion_robot/move_to_height" if case == "height_nan" else "/insertion_robot/insert"
                a = actionlib.SimpleActionClient(action, LinearMoveAction)
                a.wait_for_server(rospy.Duration(30))
                goal = {"insert_nan_target": LinearMoveGoal(target_m=float("nan"), velocity_m_s=0.001),
                        "insert_inf_velocity": LinearMoveGoal(target_m=0.01, velocity_m_s=float("inf")),
                        "height_nan": LinearMoveGoal(target_m=float("nan"), velocity_m_s=0.001)}[case]
                a.send_goal(goal)
                a.wait_for_result(rospy.Duration(5))
                refused, detail = goal_refused(a)
                record(case, refused, detail, expect=["nan", "inf", "finite"])
            elif case == "flip_nan_velocity":
                a = actionlib.SimpleActionClient("/insertion_robot/flip_bevel", FlipBevelAction)
                a.wait_for_server(rospy.Duration(30))
                a.send_goal(FlipBevelGoal(velocity_rad_s=float("nan")))
                a.wait_for_result(rospy.Duration(5))
                refused, detail = goal_refused(a)
                record(case, refused, detail, expect=["nan", "finite", "velocity"])
            elif case in ("policy_nan_tip", "policy_inf_tip", "policy_nan_theta"):
                pose = {"policy_nan_tip": Pose2D(float("nan"), 0.0, 0.0),
                        "policy_inf_tip": Pose2D(0.01, float("inf"), 0.0),
                        "policy_nan_theta": Pose2D(0.01, 0.0, float("nan"))}[case]
                c = policy_answer(pose)
                record(case, c is not None and c.status == "invalid_tip" and c.control == "",
                       "no answer" if c is None else f"{c.status} {c.control}")
            elif case == "entry_pose_nan":
                r = call("/insertion_robot/set_entry_pose", SetEntryPose,
                         SetEntryPoseRequest(height_m=float("nan"), angle_rad=0.0, bevel="left"))
                record(case, not r.success, r.message, expect=["finite", "nan"])
            elif case == "entry_pose_bad_bevel":
                r = call("/insertion_robot/set_entry_pose", SetEntryPose,
                         SetEntryPoseRequest(height_m=0.0, angle_rad=0.0, bevel="sideways"))
                record(case, not r.success, r.message)
            elif case == "plan_dwells_bad_method":
                r = call("/dwell_scheduler/plan", PlanDwells, PlanDwellsRequest(synthetic_seed=1, method="magic"))
                record(case, not r.success, r.message)
            elif case == "plan_dwells_bad_id":
                r = call("/dwell_scheduler/plan", PlanDwells, PlanDwellsRequest(synthetic_seed=1, plan_id="../etc/x"))
                record(case, not r.success, r.message)
            elif case == "evaluate_nan":
                plan = call("/dwell_scheduler/plan", PlanDwells, PlanDwellsRequest(synthetic_seed=2))
                ch = plan.plan.schedule.channels[0]
                r = call("/dwell_scheduler/evaluate", EvaluateDelivery,
                         EvaluateDeliveryRequest(plan_id=plan.plan.plan_id, channel=[ch.channel],
                                                 dwell_index=[ch.dwell_index[0]],
                                                 delivered_s=[float("nan")]))
                record(case, not r.success, r.message, expect=["finite", "nan"])
            elif case == "deliver_nan_time":
                deadline = time.time() + 120  # the procedure's delivery ends first
                while time.time() < deadline:
                    st = rospy.wait_for_message("/afterloader/state", AfterloaderState, 5)
                    if st.state not in ("DELIVERING", "PAUSED"):
                        break
                    time.sleep(0.5)
                a = actionlib.SimpleActionClient("/afterloader/deliver", DeliverAction)
                a.wait_for_server(rospy.Duration(30))
                g = DeliverGoal()
                g.schedule.plan_id = "fault_campaign_nan"
                g.schedule.channels = [DwellChannel(channel=1, catheter="c", length_m=1.2,
                                                    transfer_length_m=1.0, distance_m=[1.1],
                                                    dwell_index=[0], time_s=[float("nan")],
                                                    position=[Point(0, 0, 0)])]
                g.schedule.plan_air_kerma_strength_U = 40000.0
                g.schedule.current_air_kerma_strength_U = 40000.0
                a.send_goal(g)
                a.wait_for_result(rospy.Duration(10))
                r = a.get_result()
                record(case, a.get_state() in (actionlib.GoalStatus.REJECTED, actionlib.GoalStatus.ABORTED)
                       or (r is not None and r.status in ("refused", "aborted")),
                       f"state {a.get_state()}: {a.get_goal_status_text()} {r.status if r else ''} "
                       f"{r.message if r else ''}", expect=["finite", "nan", "time"])
            elif case == "plan_rigid_nan":
                r = call("/rigid_planner/plan", PlanRigid, PlanRigidRequest(target=Point(float("nan"), 0.0, 0.0)))
                record(case, not r.success, r.message, expect=["finite", "nan"])
            elif case == "plan_rigid_outside":
                r = call("/rigid_planner/plan", PlanRigid, PlanRigidRequest(target=Point(5.0, 5.0, 0.0)))
                record(case, not r.success, r.message)
            else:
                record(case, False, "unknown case")
        except Exception as e:  # noqa: BLE001 - a sender failure counts as not refused
            record(case, False, f"sender error: {type(e).__name__}: {e}")
    with open(out_path, "w") as f:
        json.dump(results, f)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=False)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--runs", type=int, default=0, help="kill runs (default 42, --quick 14)")
    ap.add_argument("--skip-bad", action="store_true", help="kill runs only (debugging)")
    ap.add_argument("--skip-kills", action="store_true", help="bad inputs only (debugging)")
    ap.add_argument("--procedures", default="", help="comma-separated subset (debugging)")
    ap.add_argument("--probe")
    ap.add_argument("--send-bad", nargs="+")
    a = ap.parse_args()
    if a.probe:
        return probe_main(a.probe)
    if a.send_bad:
        return send_bad_main(a.send_bad[0], a.send_bad[1:])
    out = a.out
    os.makedirs(out, exist_ok=True)
    rng = random.Random(a.seed)
    n = a.runs or (14 if a.quick else 42)
    # Every (procedure, node) pair in turn, then seeded random ones.
    chosen = set(a.procedures.split(",")) if a.procedures else set(PROCEDURES)
    pairs = [(p, node) for p, spec in PROCEDURES.items() for node in spec["nodes"] if p in chosen]
    plan = pairs[:n] + [rng.choice(pairs) for _ in range(max(0, n - len(pairs)))]
    if a.skip_kills:
        plan = []
    records = []
    t0 = time.time()
    for i, (p, node) in enumerate(plan):
        rec = kill_run(out, p, PROCEDURES[p], node, rng, i)
        print(f"[faults] run {i + 1}/{len(plan)}: {p}, kill /{node}: hang {rec['hang']}, named "
              f"{rec['named']}, detect {rec['detect_s']} s, exit {rec['exit_s']} s, "
              f"unsafe '{rec['unsafe']}', lost {rec['lost']} — {rec['outcome']}", flush=True)
        records.append(rec)
    bad = []
    if not a.skip_bad:
        for k, spec in enumerate(BAD_INPUT_RUNS):
            bad += bad_input_run(out, rng, len(plan) + k, spec)
        bad.append(stale_parameter_run(out, rng, len(plan) + len(BAD_INPUT_RUNS)))
    for b in bad:
        print(f"[faults] bad input {b['case']}: {'refused' if b['refused'] else 'NOT REFUSED'} — {b['detail']}")

    done = [r for r in records if not r.get("skipped")]
    detects = [r["detect_s"] for r in done if isinstance(r["detect_s"], float) and math.isfinite(r["detect_s"])]
    summary = dict(
        runs=len(done),
        runs_skipped=len(records) - len(done),
        hangs=sum(r["hang"] for r in done),
        reports_naming_cause=round(sum(r["named"] for r in done) / max(1, len(done)), 4),
        max_detect_s=max(detects) if detects else None,
        detect_measured_runs=len(detects),
        unsafe_device_states=sum(1 for r in done if r["unsafe"]),
        lost_journal_entries=sum(r["lost"] for r in done),
        bad_inputs=len(bad),
        refused_bad_inputs_fraction=round(sum(b["refused"] for b in bad) / max(1, len(bad)), 4),
        seed=a.seed,
        wall_s=round(time.time() - t0, 1),
    )
    keys = ["run", "procedure", "fault", "node", "kill_after_running_s", "hang", "named",
            "detect_s", "exit_s", "unsafe", "lost", "outcome"]
    with open(os.path.join(out, "faults.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        w.writerows(records)
    with open(os.path.join(out, "bad_inputs.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["case", "refused", "detail"])
        w.writeheader()
        w.writerows(bad)
    with open(os.path.join(out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    plot(out, done)
    print(json.dumps(summary, indent=2))


def plot(out, records):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(8, 4.5))
    procs = sorted({r["procedure"] for r in records})
    for k, p in enumerate(procs):
        xs = [r["exit_s"] for r in records if r["procedure"] == p]
        ds = [r["detect_s"] for r in records if r["procedure"] == p]
        ax.scatter(xs, [k] * len(xs), marker="o", label="kill -> procedure exit" if k == 0 else None, color="C0")
        ax.scatter(ds, [k + 0.15] * len(ds), marker="x", label="kill -> detected" if k == 0 else None, color="C3")
    ax.axvline(2.0, color="C3", ls="--", lw=1, label="detect target 2 s")
    ax.axvline(HANG_S, color="k", ls=":", lw=1, label="hang limit 30 s")
    ax.set_yticks(range(len(procs)))
    ax.set_yticklabels(procs)
    ax.set_xlabel("seconds after the SIGKILL")
    ax.set_title("Fault campaign: detection and exit per run")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "faults.png"), dpi=110)


if __name__ == "__main__":
    sys.exit(main())
