# find_package(vlff-shm): the controller library as imported targets,
#   vlff-shm::vlff-shm         libvlff-shm.so (link this one)
#   vlff-shm::vlff-shm-static  libvlff-shm.a
# with the header's directory in their include path. An executable linked
# to the shared one runs from its build tree (CMake's build run path names
# the library's directory); once installed it needs INSTALL_RPATH, or
# CMAKE_INSTALL_RPATH_USE_LINK_PATH, unless the library is under /usr.
include(CMakeFindDependencyMacro)
find_dependency(Threads)
include("${CMAKE_CURRENT_LIST_DIR}/vlff-shm-targets.cmake")
