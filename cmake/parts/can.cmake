# can/: MM3E frame codec, transports, driver and simulated-device cores, their nodes and tests.
piezo_unit_test(test_can_codec test/unit/test_can_codec.cpp)
piezo_unit_test(test_can_limiter test/unit/test_can_limiter.cpp)
piezo_unit_test(test_can_driver test/unit/test_can_driver.cpp)
piezo_node(mm3e_driver src/nodes/mm3e_driver_node.cpp)
piezo_node(mm3e_sim src/nodes/mm3e_sim_node.cpp)
