# compensation/ + the predictor node: inverse, drift forecast, per-axis compensator, node, rostests, benchmark.
piezo_unit_test(test_compensation_core test/unit/test_compensation_core.cpp)
piezo_node(piezo_predictor src/nodes/piezo_predictor_node.cpp)
