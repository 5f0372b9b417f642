# recorder: data-collection node, `piezo record`, recording summary.
piezo_unit_test(test_recording_summary test/unit/test_recording_summary.cpp)
piezo_ros_unit_test(test_recording_bag test/unit/test_recording_bag.cpp)
piezo_node(piezo_recorder src/nodes/piezo_recorder_node.cpp)
# Runs the simulated device and the driver on simulated time: a few minutes at time_scale 10.
piezo_rostest(test/rostest/recorder_protocols.test test/rostest/recorder_protocols.cpp
              DEPENDS piezo_recorder mm3e_sim mm3e_driver)
if(CATKIN_ENABLE_TESTING)
  # Parameter layer: wrong type / out of range / unknown names (the same checker, only the master needed).
  piezo_add_rostest(test/rostest/recorder_params.test DEPENDENCIES recorder_protocols)
endif()
# The recorder owns /clock and steps the simulated device (lock-step): about a minute.
piezo_rostest(test/rostest/recorder_lockstep.test test/rostest/recorder_lockstep.cpp
              DEPENDS piezo_recorder mm3e_sim mm3e_driver)
