# compensation/ + the predictor node: inverse, drift forecast, per-axis compensator, node, rostests, benchmark.
piezo_unit_test(test_compensation_core test/unit/test_compensation_core.cpp)
piezo_node(piezo_predictor src/nodes/piezo_predictor_node.cpp)
piezo_benchmark(bench_compensation bench/bench_compensation.cpp)
# Node processing measured on a bag (not Google Benchmark; `piezo bench` runs it with its defaults).
add_executable(measure_predictor_node bench/measure_predictor_node.cpp)
target_link_libraries(measure_predictor_node piezo_ros piezo_core ${catkin_LIBRARIES})
target_compile_definitions(measure_predictor_node PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
add_dependencies(measure_predictor_node ${PROJECT_NAME}_generate_messages_cpp)
set_target_properties(measure_predictor_node PROPERTIES
  RUNTIME_OUTPUT_DIRECTORY ${CATKIN_DEVEL_PREFIX}/lib/${PROJECT_NAME}/bench)
piezo_rostest(test/rostest/predictor_fallback.test test/rostest/predictor_fallback.cpp DEPENDS piezo_predictor)
piezo_rostest(test/rostest/predictor_live.test test/rostest/predictor_live.cpp DEPENDS piezo_predictor)
piezo_node(piezo_demo src/nodes/piezo_demo_node.cpp)
piezo_rostest(test/rostest/predictor_replay.test test/rostest/predictor_replay.cpp DEPENDS piezo_predictor)
piezo_rostest(test/rostest/predictor_inputs.test test/rostest/predictor_inputs.cpp DEPENDS piezo_predictor)
piezo_rostest(test/rostest/predictor_params.test test/rostest/predictor_params.cpp)
piezo_unit_test(test_compensation_watch test/unit/test_compensation_watch.cpp)
piezo_ros_unit_test(test_predictor_snapshot test/unit/test_predictor_snapshot.cpp)
