"""The Fast DDS profile of the image publishers: a shared-memory segment that holds several stereo frames,
applied only when the user chose no profile and no other middleware."""

from __future__ import annotations

import xml.etree.ElementTree as ET

from fixego_ros.nodes.dds_profile import PROFILE_ENV, profile_path, use_image_profile

NS = {'f': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
VGA_STEREO_BYTES = 2 * 640 * 480


def test_the_profile_gives_a_default_participant_a_segment_of_several_stereo_frames():
    root = ET.parse(profile_path()).getroot()
    shm = [d for d in root.iterfind('f:transport_descriptors/f:transport_descriptor', NS)
           if d.findtext('f:type', namespaces=NS) == 'SHM']
    assert len(shm) == 1
    assert int(shm[0].findtext('f:segment_size', namespaces=NS)) >= 8 * VGA_STEREO_BYTES
    (participant,) = root.iterfind('f:participant', NS)
    assert participant.get('is_default_profile') == 'true'
    used = [t.text for t in participant.iterfind('f:rtps/f:userTransports/f:transport_id', NS)]
    assert shm[0].findtext('f:transport_id', namespaces=NS) in used
    assert any(d.findtext('f:type', namespaces=NS) == 'UDPv4' and d.findtext('f:transport_id', namespaces=NS) in used
               for d in root.iterfind('f:transport_descriptors/f:transport_descriptor', NS))  # other hosts still
    assert participant.findtext('f:rtps/f:useBuiltinTransports', namespaces=NS) == 'false'


def test_applied_when_nothing_is_set():
    env: dict[str, str] = {}
    note = use_image_profile(env)
    assert all(env[name] == str(profile_path()) for name in PROFILE_ENV)
    assert str(profile_path()) in note
    env = {'RMW_IMPLEMENTATION': 'rmw_fastrtps_cpp'}
    use_image_profile(env)
    assert env[PROFILE_ENV[0]] == str(profile_path())


def test_the_users_profile_and_other_middlewares_are_left_alone():
    env = {PROFILE_ENV[0]: '/etc/my_dds.xml'}
    note = use_image_profile(env)
    assert env == {PROFILE_ENV[0]: '/etc/my_dds.xml'} and '/etc/my_dds.xml' in note
    env = {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}
    note = use_image_profile(env)
    assert env == {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'} and 'rmw_cyclonedds_cpp' in note
