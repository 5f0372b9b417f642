# The operator's side: CLI option parsing, the strip-chart monitor node, the demo scenarios.
piezo_unit_test(test_cli_args test/unit/test_cli_args.cpp)
# sim.launch with no arguments, and with a broken model file for one axis (same checker). Needs the shipped
# models; without them the no-argument launch runs those axes in fallback, which the test would report as failures.
set(PIEZO_DEFAULT_MODELS_PRESENT TRUE)
foreach(axis a b c)
  if(NOT EXISTS ${CMAKE_CURRENT_SOURCE_DIR}/config/models/mm3e_sim_${axis}.yaml)
    set(PIEZO_DEFAULT_MODELS_PRESENT FALSE)
    message(WARNING "config/models/mm3e_sim_${axis}.yaml missing (scripts/make-default-models makes it): "
                    "rostests sim_launch and sim_launch_broken_model are not registered")
  endif()
endforeach()
if(CATKIN_ENABLE_TESTING AND PIEZO_DEFAULT_MODELS_PRESENT)
  add_rostest_gtest(sim_launch_check test/rostest/sim_launch.test test/rostest/sim_launch_check.cpp)
  target_link_libraries(sim_launch_check ${catkin_LIBRARIES})
  add_dependencies(sim_launch_check ${PROJECT_NAME}_generate_messages_cpp piezo_predictor piezo_monitor mm3e_driver mm3e_sim)
  piezo_rostest_budget(test/rostest/sim_launch.test)
  piezo_add_rostest(test/rostest/sim_launch_broken_model.test DEPENDENCIES sim_launch_check)
endif()
piezo_unit_test(test_strip_chart test/unit/test_strip_chart.cpp)
piezo_node(piezo_monitor src/nodes/piezo_monitor_node.cpp)
piezo_unit_test(test_demo_scenario test/unit/test_demo_scenario.cpp)
# The demo's lock-step path (sawtooth only, ~10 s): the demo paces the device, no command late.
if(CATKIN_ENABLE_TESTING AND PIEZO_DEFAULT_MODELS_PRESENT)
  add_rostest_gtest(demo_lockstep_check test/rostest/demo_lockstep.test test/rostest/demo_lockstep_check.cpp)
  target_link_libraries(demo_lockstep_check ${catkin_LIBRARIES} yaml-cpp)
  add_dependencies(demo_lockstep_check piezo_demo piezo_predictor mm3e_driver mm3e_sim)
  piezo_rostest_budget(test/rostest/demo_lockstep.test)
endif()
