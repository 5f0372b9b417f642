# can/: MM3E frame codec, transports, driver and simulated-device cores, their nodes and tests.
piezo_unit_test(test_can_codec test/unit/test_can_codec.cpp)
piezo_unit_test(test_can_limiter test/unit/test_can_limiter.cpp)
piezo_unit_test(test_can_driver test/unit/test_can_driver.cpp)
piezo_node(mm3e_driver src/nodes/mm3e_driver_node.cpp)
piezo_node(mm3e_sim src/nodes/mm3e_sim_node.cpp)
# One checker executable; each .test file is one safety behaviour and selects its case with --gtest_filter.
piezo_rostest(test/rostest/driver_topics.test test/rostest/driver_rostest.cpp DEPENDS mm3e_driver mm3e_sim)
if(CATKIN_ENABLE_TESTING)
  foreach(behaviour command clamp slew nan timeout bus_fault commanders)
    add_rostest(test/rostest/driver_${behaviour}.test DEPENDENCIES driver_topics mm3e_driver mm3e_sim)
  endforeach()
endif()
