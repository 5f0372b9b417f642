# nanocontrol/: the Kleindiek NanoControl serial line protocol, its transport below can::DriverCore, the simulated
# device on a pseudo-terminal (docs/nanocontrol.md), and their tests.
piezo_unit_test(test_nanocontrol_line test/unit/test_nanocontrol_line.cpp)
piezo_unit_test(test_nanocontrol_link test/unit/test_nanocontrol_link.cpp)
