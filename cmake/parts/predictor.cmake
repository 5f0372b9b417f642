# compensation/ + the predictor node: inverse, drift forecast, per-axis compensator, node, rostests, benchmark.
piezo_unit_test(test_compensation_core test/unit/test_compensation_core.cpp)
