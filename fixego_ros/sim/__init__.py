"""The simulated rig (ROS-free except the bag serialisation): a textured room (``world``), exact pinhole
rendering (``render``), rig trajectories (``trajectories``), a model of the fixation servo
(``servo_model``), the rig's vergence step (``vergence_step``, ``vergence_on_point``,
``vergence_measure``), the frame loop (``run``) and the image-level bag writer behind ``fixego sim``
(``bag_writer``, ``cli``). The live counterpart is ``fixego_ros.nodes.sim_rig_node``."""
