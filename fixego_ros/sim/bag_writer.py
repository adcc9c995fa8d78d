"""Write a simulated sequence as an image-level rosbag2/MCAP bag with the topic contract of DESIGN.md §3.

Storage and ``metadata.yaml`` come from ``rosbags`` (rosbag2 format version 9, with offered QoS
profiles and RIHS01 type hashes, which is what ``ros2 bag info/play`` expect; the MCAP file gets real
CRCs from :mod:`fixego_ros.bags.mcap_storage`, so bit rot is detected when reading); the messages are real
ROS 2 messages serialised to CDR by rclpy, so what a subscriber gets from ``ros2 bag play`` is
value-identical to what the nodes would publish (alignment padding is zeroed for reproducibility,
see :func:`canonical_cdr`).

Topics (namespace ``/fixego``): ``{right,left}/image_raw``, ``{right,left}/camera_info``,
``{right,left}/joint_states`` (the readings, quantised as VISCA reports them, with their 1-sigma in ``effort`` as
camera_node states it: unit / sqrt 12), ``ground_truth/pose`` and, simulator only,
``ground_truth/{right,left}/fixation`` (geometry_msgs/PointStamped: ``point.x, point.y`` = true pixel
of the servo's fixation point, no message while it is behind the camera; ``point.z`` = fixation id, which
increases by one at each re-selection).

Optional (``wheel_odom``, off by default, so the default output is unchanged byte for byte):
``wheel/odom`` (nav_msgs/Odometry, frame ``odom``, child ``base_link``), one per frame and written before
the frame's images, or at ``rate_hz`` (each written before the first frame at or after its stamp): the true
``base_link`` linear velocity in ``base_link`` (finite differences of the true poses,
:meth:`~fixego_ros.sim.run.Simulation.base_velocities`), times ``1 + scale_bias``, plus seeded Gaussian noise of
std ``std_m_s`` per axis (:mod:`fixego_ros.sim.wheel_odometry`), with covariance diag(std²) on the linear part (at
least (1e-4 m/s)², so it never reads as "unknown"; the bias is not in it, as on a robot). The angular part is not
measured: zero with variance 1e6. The pose is left at identity with variance 1e6 (a speed source only).

Vergence (``SimSettings.vergence``; ``off`` writes nothing new, so its output is unchanged byte for byte):
``vergence`` (geometry_msgs/PoseWithCovarianceStamped, frame ``rig``, offered as transient local like
camera_node's latched one), one message per vergence measurement (at the first frame and at each new right
fixation, when the step succeeds), stamped with the frame the measurement refers to and written before that
frame's images (after its wheel odometry sample): the right camera's fixation point in the rig frame at that
stamp, triangulated from both heads' quantised joint readings and the point's noisy pixels, with its
first-order covariance in the position block (orientation identity, variance 1e6); see
:mod:`fixego_ros.sim.vergence_measure`. ``physical`` also moves the left head (its images, joint states and
ground-truth fixation show the step: :mod:`fixego_ros.sim.vergence_step`); ``measurements`` leaves the heads
alone. ``sim.yaml`` gets a ``vergence`` block: every measurement with its true distance and error, the steps
that gave none and why, and (``physical``) each step's times.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from fixego_ros.geometry.rig import Rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.pipeline.odometry import MIN_STD
from fixego_ros.progress import Progress
from fixego_ros.sim.run import Frame, SimSettings, Simulation
from fixego_ros.sim.vergence_measure import input_sigmas
from fixego_ros.sim.vergence_step import VergenceStep
from fixego_ros.sim.wheel_odometry import WheelOdometry

NS = '/fixego'
SIDES = ('right', 'left')
WHEEL_ODOM_TOPIC = f'{NS}/wheel/odom'
UNKNOWN_VARIANCE = 1e6
VERGENCE_TOPIC = f'{NS}/vergence'


def topics(wheel_odom: bool = False, vergence: bool = False) -> dict[str, str]:
    """Topic -> message type of a simulated bag, in writing order (connections in this order)."""
    out = {f'{NS}/ground_truth/pose': 'geometry_msgs/msg/PoseStamped'}
    for side in SIDES:
        out[f'{NS}/{side}/image_raw'] = 'sensor_msgs/msg/Image'
        out[f'{NS}/{side}/camera_info'] = 'sensor_msgs/msg/CameraInfo'
        out[f'{NS}/{side}/joint_states'] = 'sensor_msgs/msg/JointState'
        out[f'{NS}/ground_truth/{side}/fixation'] = 'geometry_msgs/msg/PointStamped'
    if wheel_odom:
        out[WHEEL_ODOM_TOPIC] = 'nav_msgs/msg/Odometry'
    if vergence:
        out[VERGENCE_TOPIC] = 'geometry_msgs/msg/PoseWithCovarianceStamped'
    return out


def wheel_odom_msg(t: float, v_base: np.ndarray, std: float):
    """nav_msgs/Odometry carrying the linear velocity ``v_base`` (base_link, m/s) with variance ``std``²."""
    from nav_msgs.msg import Odometry

    from fixego_ros.nodes.common import sec_to_stamp
    msg = Odometry()
    msg.header.stamp = sec_to_stamp(t)
    msg.header.frame_id = 'odom'
    msg.child_frame_id = 'base_link'
    msg.pose.pose.orientation.w = 1.0
    pose_cov = np.diag([UNKNOWN_VARIANCE] * 6)
    var = max(std, MIN_STD) ** 2        # never all zeros: that would mean "unknown" (REP-105 practice)
    twist_cov = np.diag([var] * 3 + [UNKNOWN_VARIANCE] * 3)
    msg.pose.covariance = [float(x) for x in pose_cov.ravel()]
    msg.twist.covariance = [float(x) for x in twist_cov.ravel()]
    lin = msg.twist.twist.linear
    lin.x, lin.y, lin.z = (float(x) for x in v_base)
    return msg


def camera_info_msg(rig: Rig, side: str, t: float):
    from sensor_msgs.msg import CameraInfo

    from fixego_ros.nodes.common import sec_to_stamp
    cam = rig.camera(side)
    msg = CameraInfo()
    msg.header.stamp = sec_to_stamp(t)
    msg.header.frame_id = f'{side}_optical_frame'
    msg.width, msg.height = cam.width, cam.height
    msg.distortion_model = 'plumb_bob'
    msg.d = [float(x) for x in cam.dist]
    msg.k = [float(x) for x in cam.K.ravel()]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def pose_msg(pose: Pose, t: float, frame_id: str = 'odom'):
    from geometry_msgs.msg import PoseStamped

    from fixego_ros.nodes.common import pose_to_msg, sec_to_stamp
    msg = PoseStamped()
    msg.header.stamp = sec_to_stamp(t)
    msg.header.frame_id = frame_id
    pose_to_msg(pose, msg.pose)
    return msg


def frame_messages(frame: Frame, rig: Rig, epoch: float, encoding: str) -> list[tuple[str, object]]:
    """(topic, message) pairs of one frame, in a fixed order."""
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState

    from fixego_ros.nodes.common import array_to_image, sec_to_stamp

    t = epoch + frame.t
    out: list[tuple[str, object]] = [(f'{NS}/ground_truth/pose', pose_msg(frame.gt_base, t))]
    for side in SIDES:
        st = frame.states[side]
        stamp = sec_to_stamp(t)
        im = array_to_image(frame.images[side], stamp, f'{side}_optical_frame', encoding)
        js = JointState()
        js.header.stamp = stamp
        js.name = [f'{side}_pan', f'{side}_tilt']
        js.position = [float(st.pan_reading), float(st.tilt_reading)]
        js.effort = [float(v) for v in st.reading_sigmas]     # their 1-sigma, where camera_node puts it
        out += [(f'{NS}/{side}/image_raw', im), (f'{NS}/{side}/camera_info', camera_info_msg(rig, side, t)),
                (f'{NS}/{side}/joint_states', js)]
        if np.all(np.isfinite(st.pixel)):   # no message (never NaN) while the point is behind the camera
            fx = PointStamped()
            fx.header.stamp = stamp
            fx.header.frame_id = f'{side}_optical_frame'
            fx.point.x, fx.point.y = float(st.pixel[0]), float(st.pixel[1])
            fx.point.z = float(st.fixation_id)
            out.append((f'{NS}/ground_truth/{side}/fixation', fx))
    return out


def _qos(sensor: bool, latched: bool = False):
    """Offered QoS of a topic: sensor data, reliable, or latched (transient local with camera_node's depth,
    LATCHED_QOS: a player keeps that many vergence measurements for late subscribers)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    from fixego_ros.nodes.common import LATCHED_QOS
    infinite = QosTime(9223372036, 854775807)
    return Qos(QosHistory.KEEP_LAST, LATCHED_QOS.depth if latched else 5 if sensor else 10,
               QosReliability.BEST_EFFORT if sensor else QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               infinite, infinite, QosLiveliness.AUTOMATIC, infinite, False)


def canonical_cdr(msg, msgtype: str, typestore) -> bytes:
    """rclpy's CDR encoding of ``msg`` with zeroed alignment padding and no trailing bytes.

    rclpy (Fast-CDR) leaves padding bytes uninitialised and may append a few junk bytes after the
    message (which ``rosbags``' strict reader rejects), so the same message would serialise to
    different bytes from run to run. Re-encoding the decoded fields through rosbags fixes both; the
    result is checked to decode with rclpy to exactly the original message.
    """
    from rclpy.serialization import deserialize_message, serialize_message

    raw = serialize_message(msg)
    msgdef = typestore.get_msgdef(msgtype)
    decoder = msgdef.deserialize_cdr_le if raw[1] == 1 else msgdef.deserialize_cdr_be
    fields, _ = decoder(raw[4:], 0, msgdef.cls, typestore)
    out = bytes(typestore.serialize_cdr(fields, msgtype, little_endian=raw[1] == 1))
    back = deserialize_message(out, type(msg))
    if back != msg:
        raise ValueError(f'{msgtype}: CDR re-encoding changed the message')
    return out


@dataclass
class BagSummary:
    path: Path
    frames: int
    messages: int
    duration_s: float
    bytes: int
    reselections: dict[str, int]
    wall_s: float
    vergence: int = 0         # vergence measurements written


def vergence_record(sim: Simulation, settings: SimSettings) -> dict:
    """The ``vergence`` block of ``sim.yaml``: the model's constants, every measurement (true distance and
    error), the steps without one and, for ``physical``, each step's times."""
    verg = sim.vergence
    assert verg is not None
    p = verg.p
    servo = sim.servos['left'].p
    fixed, _ = input_sigmas(servo, p.pixel_sigma_px)
    epoch = settings.epoch
    out: dict[str, object] = {
        'mode': settings.vergence, 'topic': VERGENCE_TOPIC, 'pixel_sigma_px': p.pixel_sigma_px,
        'reading_sigma_deg': {'pan': float(np.degrees(fixed[0])), 'tilt': float(np.degrees(fixed[1]))},
        'control_hz': p.control_hz, 'window_ticks': 2 * p.hold_ticks + 1,
        'measurements': [m.record(epoch) for m in verg.measurements],
        'failures': [{'stamp_s': float(epoch + f['t']), 'right_fixation_id': f['right_fixation_id'],
                      'reason': f['reason']} for f in verg.failures]}
    if isinstance(verg, VergenceStep):
        out['steps'] = [s.record(epoch) for s in verg.steps]
    return out


def write_bag(out_dir: str | Path, rig: Rig, settings: SimSettings | None = None, progress: bool = True,
              sim: Simulation | None = None, wheel_odom: WheelOdometry | None = None) -> BagSummary:
    """Simulate ``settings`` on ``rig`` and write the bag directory ``out_dir`` (must not exist);
    ``wheel_odom`` adds the simulated wheel odometry topic, ``settings.vergence`` the vergence
    measurements (module docstring)."""
    settings = settings or (sim.s if sim is not None else SimSettings())
    if wheel_odom is not None and (why := wheel_odom.problems()):
        raise ValueError('; '.join(why))
    from rosbags.typesys import Stores, get_typestore

    from fixego_ros.bags.mcap_storage import bag_writer
    from fixego_ros.nodes.common import sec_to_stamp, vergence_to_msg

    out_dir = Path(out_dir)
    if out_dir.exists():
        raise FileExistsError(f'{out_dir} exists already; rosbag2 directories are never overwritten')
    sim = sim or Simulation(rig, settings)
    wheel = wheel_odom.samples(sim, settings.seed) if wheel_odom is not None else None
    n_wheel = 0                       # samples written so far
    vergence = sim.vergence is not None
    typestore = get_typestore(Stores.ROS2_JAZZY)
    wall0 = time.monotonic()
    bar = Progress(len(sim), f'fixego sim {settings.trajectory}', progress)
    n_msgs = n_verg = 0
    writer = bag_writer(out_dir)     # zstd MCAP chunks, as rosbag2's; with chunk, data and summary CRCs
    with writer:
        writer.set_custom_data('fixego_sim', ' '.join(f'{k}={v}' for k, v in settings.to_dict().items()))
        if wheel_odom is not None:
            writer.set_custom_data('fixego_sim_wheel_odom_std', f'{wheel_odom.std_m_s}')
            if wheel_odom.rate_hz is not None or wheel_odom.scale_bias:
                writer.set_custom_data('fixego_sim_wheel_odom', f'rate_hz={wheel_odom.rate_hz} '
                                                                f'scale_bias={wheel_odom.scale_bias}')
        conns = {topic: writer.add_connection(topic, msgtype, typestore=typestore,
                                              offered_qos_profiles=[_qos(topic.endswith('image_raw'),
                                                                         topic == VERGENCE_TOPIC)])
                 for topic, msgtype in topics(wheel is not None, vergence).items()}
        for frame in sim.frames():
            stamp_ns = round((settings.epoch + frame.t) * 1e9)
            t = settings.epoch + frame.t
            msgs = [(topic, msg, stamp_ns) for topic, msg in frame_messages(frame, rig, settings.epoch,
                                                                             settings.encoding)]
            if frame.vergence is not None:   # before the images: replay gives it to the estimator first
                m = frame.vergence
                msgs.insert(0, (VERGENCE_TOPIC, vergence_to_msg(sec_to_stamp(t), m.point_rig, m.cov_rig), stamp_ns))
                n_verg += 1
            if wheel is not None:            # first of all, as before: the samples up to this frame, in order
                times, v = wheel
                due = int(np.searchsorted(times, frame.t + 1e-9, side='right'))
                msgs[:0] = [(WHEEL_ODOM_TOPIC, wheel_odom_msg(settings.epoch + times[j], v[j], wheel_odom.std_m_s),
                             round((settings.epoch + times[j]) * 1e9)) for j in range(n_wheel, due)]
                n_wheel = due
            for topic, msg, log_ns in msgs:
                writer.write(conns[topic], log_ns, canonical_cdr(msg, conns[topic].msgtype, typestore))
                n_msgs += 1
            bar.update(frame.index + 1)
    rig.save(out_dir / 'rig.yaml')
    meta = {'simulator': settings.to_dict(),
            'topics_simulator_only': [f'{NS}/ground_truth/{s}/fixation' for s in SIDES],
            'step_marks_s': None if sim.trajectory.marks is None
            else [float(settings.epoch + m) for m in sim.trajectory.marks]}
    if wheel_odom is not None:
        meta['wheel_odometry'] = wheel_odom.record(WHEEL_ODOM_TOPIC)
    if vergence:
        meta['vergence'] = vergence_record(sim, settings)
    (out_dir / 'sim.yaml').write_text(yaml.safe_dump(meta, sort_keys=False))
    size = sum(f.stat().st_size for f in out_dir.iterdir() if f.is_file())
    return BagSummary(out_dir, len(sim), n_msgs, float(sim.stamps[-1]), size,
                      {s: sv.reselections for s, sv in sim.servos.items()}, time.monotonic() - wall0, n_verg)
