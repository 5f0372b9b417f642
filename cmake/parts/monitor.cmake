# The operator's side: CLI option parsing, the strip-chart monitor node, the demo scenarios.
piezo_unit_test(test_cli_args test/unit/test_cli_args.cpp)
# sim.launch with no arguments, and with a broken model file for one axis (same checker).
if(CATKIN_ENABLE_TESTING)
  add_rostest_gtest(sim_launch_check test/rostest/sim_launch.test test/rostest/sim_launch_check.cpp)
  target_link_libraries(sim_launch_check ${catkin_LIBRARIES})
  add_dependencies(sim_launch_check ${PROJECT_NAME}_generate_messages_cpp piezo_predictor mm3e_driver mm3e_sim)
  add_rostest(test/rostest/sim_launch_broken_model.test DEPENDENCIES sim_launch_check)
endif()
piezo_unit_test(test_strip_chart test/unit/test_strip_chart.cpp)
piezo_node(piezo_monitor src/nodes/piezo_monitor_node.cpp)
piezo_unit_test(test_demo_scenario test/unit/test_demo_scenario.cpp)
