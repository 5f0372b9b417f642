# recorder: data-collection node, `piezo record`, recording summary (issue 7).
piezo_unit_test(test_recording_summary test/unit/test_recording_summary.cpp)
piezo_ros_unit_test(test_recording_bag test/unit/test_recording_bag.cpp)
