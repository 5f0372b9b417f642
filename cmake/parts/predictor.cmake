# compensation/ + the predictor node: inverse, drift forecast, per-axis compensator, node, rostests, benchmark.
piezo_unit_test(test_compensation_core test/unit/test_compensation_core.cpp)
piezo_unit_test(test_estimation test/unit/test_estimation.cpp)
piezo_unit_test(test_estimation_quantised test/unit/test_estimation_quantised.cpp)
piezo_unit_test(test_estimation_forecast test/unit/test_estimation_forecast.cpp)
piezo_unit_test(test_hold_trim test/unit/test_hold_trim.cpp)
# the estimator identified on one coarse stage, tracking another (a fit and an identification: about a minute)
piezo_unit_test(test_estimation_foreign test/unit/test_estimation_foreign.cpp)
piezo_unit_test(test_tracking_trim test/unit/test_tracking_trim.cpp)
piezo_unit_test(test_sensor_reading_model test/unit/test_sensor_reading_model.cpp)
piezo_node(piezo_predictor src/nodes/piezo_predictor_node.cpp)
piezo_benchmark(bench_compensation bench/bench_compensation.cpp)
piezo_benchmark(bench_estimation bench/bench_estimation.cpp)
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
piezo_rostest(test/rostest/live_loop.test test/rostest/live_loop.cpp DEPENDS piezo_predictor mm3e_sim mm3e_driver)
# Live: hold trim on the foreign stage, lock-step (~20 s of wall each); needs the model fitted on that stage.
if(EXISTS ${CMAKE_CURRENT_SOURCE_DIR}/config/models/mm3e_foreign_c.yaml)
  piezo_rostest(test/rostest/hold_trim.test test/rostest/hold_trim_check.cpp
                DEPENDS piezo_demo piezo_predictor mm3e_sim mm3e_driver)
  target_link_libraries(hold_trim yaml-cpp)
  piezo_add_rostest(test/rostest/hold_trim_thermal.test DEPENDENCIES hold_trim)
  # the same on a coarse-encoder axis (250 nm steps), fused through the quantiser (docs/estimation.md)
  piezo_add_rostest(test/rostest/hold_trim_a.test DEPENDENCIES hold_trim)
  # the tracking trim in the closed loop on a stage whose hysteresis, creep and gain differ from the model's (~30 s)
  piezo_rostest(test/rostest/tracking_trim.test test/rostest/tracking_trim_check.cpp
                DEPENDS piezo_demo piezo_predictor mm3e_sim mm3e_driver)
  target_link_libraries(tracking_trim yaml-cpp)
else()
  message(WARNING "config/models/mm3e_foreign_c.yaml missing: rostests hold_trim, hold_trim_thermal and tracking_trim are not registered")
endif()
if(CATKIN_ENABLE_TESTING)
  # `piezo track`: the files it writes, a model file without an estimator block refused with one line, and
  # --identify-on/--write-model adding the block.
  add_test(NAME cli_track_smoke COMMAND sh -c
    "set -e; d=$(mktemp -d); \
     $<TARGET_FILE:piezo> simulate --stage ${CMAKE_CURRENT_SOURCE_DIR}/config/stages/mm3e_foreign_hold_stage.yaml --seed 104 --duration 2400 --out $d/s.csv; \
     $<TARGET_FILE:piezo> track --model ${CMAKE_CURRENT_SOURCE_DIR}/config/models/mm3e_foreign_c.yaml --data $d/s.csv --out $d/t > $d/out.txt; \
     head -1 $d/t/track.csv | grep -q '^time_s,applied_v,measured_nm,model_nm,fused_nm,fused_sigma_nm,true_nm$'; \
     test $(wc -l < $d/t/track.csv) -eq 26401; \
     grep -q 'truth within' $d/t/holds.md; grep -q within_2sigma $d/t/track.json; \
     grep -v '^estimator:' ${CMAKE_CURRENT_SOURCE_DIR}/config/models/mm3e_foreign_c.yaml | sed '/^  fuse:/,/^  method:/d' > $d/bare.yaml; \
     ! $<TARGET_FILE:piezo> track --model $d/bare.yaml --data $d/s.csv --out $d/u 2> $d/err.txt; grep -q 'has no estimator' $d/err.txt; \
     $<TARGET_FILE:piezo> track --model $d/bare.yaml --data $d/s.csv --identify-on $d/s.csv --identify-from-s 600 --write-model $d/m.yaml --out $d/v > /dev/null; \
     grep -q '^estimator:' $d/m.yaml; \
     rm -rf $d")
  piezo_test_budget(cli_track_smoke)
endif()
piezo_slow_tests(test_hold_trim test_estimation_foreign)  # test_hold_trim simulates 8 h of the foreign stage and runs the shipped Preisach model over it
# Resuming a model on the run before's recorded history (compensation/resume.h, the predictor's ~resume_from).
piezo_unit_test(test_compensation_resume test/unit/test_compensation_resume.cpp)
# The model-file checks, the transport rule for a model fitted on simulated data, and the data origin it is decided from.
piezo_unit_test(test_compensation_model_check test/unit/test_compensation_model_check.cpp)
# The real-hardware launch refuses to start without model_file_a/b/c, naming the missing one; each launch tells the
# predictor its transport (roslaunch parses only: no roscore).
if(CATKIN_ENABLE_TESTING)
  add_test(NAME launch_model_files COMMAND ${CMAKE_CURRENT_SOURCE_DIR}/scripts/check-launch-models ${CMAKE_CURRENT_SOURCE_DIR})
  piezo_test_budget(launch_model_files)
endif()
