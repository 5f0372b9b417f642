# sim/ and protocols/: the simulated MM3E, the data-collection protocols, bag I/O and `piezo simulate`.
piezo_unit_test(test_sim_physics test/unit/test_sim_physics.cpp)
piezo_unit_test(test_sim_effects test/unit/test_sim_effects.cpp)
piezo_unit_test(test_protocols_generators test/unit/test_protocols_generators.cpp)
piezo_ros_unit_test(test_bag_io test/unit/test_bag_io.cpp)
piezo_benchmark(bench_simulator bench/bench_simulator.cpp)
