# can/: MM3E frame codec, transports, driver and simulated-device cores, their nodes and tests.
piezo_unit_test(test_can_codec test/unit/test_can_codec.cpp)
piezo_unit_test(test_can_limiter test/unit/test_can_limiter.cpp)
piezo_unit_test(test_can_driver test/unit/test_can_driver.cpp)
