# The README's simulator recipes (every ```sh block after `<!-- recipe: offline -->`), run as written in a fresh
# directory by scripts/readme-recipes with this build's CLI. The README keeps them short enough for this test.
if(CATKIN_ENABLE_TESTING)
  add_test(NAME readme_recipes COMMAND ${CMAKE_CURRENT_SOURCE_DIR}/scripts/readme-recipes
           ${CMAKE_CURRENT_SOURCE_DIR}/README.md)
  set_tests_properties(readme_recipes PROPERTIES ENVIRONMENT "PIEZO_BIN=$<TARGET_FILE:piezo>")
  piezo_test_budget(readme_recipes SLOW)
endif()
