# nanocontrol/: the Kleindiek NanoControl serial line protocol, its transport below can::DriverCore, the simulated
# device on a pseudo-terminal (docs/nanocontrol.md), and their tests.
piezo_unit_test(test_nanocontrol_line test/unit/test_nanocontrol_line.cpp)
piezo_unit_test(test_nanocontrol_link test/unit/test_nanocontrol_link.cpp)
# rostests over a pseudo-terminal: one checker, one .test file per behaviour (--gtest_filter), as for the CAN driver
piezo_rostest(test/rostest/nanocontrol_topics.test test/rostest/nanocontrol_rostest.cpp DEPENDS mm3e_driver mm3e_sim)
if(CATKIN_ENABLE_TESTING)
  foreach(behaviour error_reply lost_reply breakdown port_lost)
    piezo_add_rostest(test/rostest/nanocontrol_${behaviour}.test DEPENDENCIES nanocontrol_topics mm3e_driver mm3e_sim)
  endforeach()
  piezo_add_rostest(test/rostest/nanocontrol_predictor.test
                    DEPENDENCIES nanocontrol_topics mm3e_driver mm3e_sim piezo_predictor)
endif()
piezo_rostest(test/rostest/nanocontrol_recorder.test test/rostest/nanocontrol_recorder.cpp DEPENDS mm3e_driver mm3e_sim)
