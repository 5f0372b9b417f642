# analysis/residual*: the residual loop (issue 8), its augmented model kind, tests.
piezo_unit_test(test_residual_stats test/unit/test_residual_stats.cpp)
piezo_unit_test(test_residual_augmented test/unit/test_residual_augmented.cpp)
piezo_unit_test(test_residual_loop test/unit/test_residual_loop.cpp)
piezo_unit_test(test_residual_sim test/unit/test_residual_sim.cpp)
piezo_unit_test(test_eval_stream test/unit/test_eval_stream.cpp)
piezo_unit_test(test_residual_gain test/unit/test_residual_gain.cpp)
