# The digest of the native core's C++ sources (ftc._core: cpp/plant/core and
# cpp/plant/bindings), as ftc.common.source_key computes it in a checkout
# (native_source_digest, NATIVE_DIRS): SHA-256 of one line
# "relative/path sha256" per file under those directories, the path relative
# to cpp/plant, sorted by path. An installed package has no sources, so its
# install writes the digest beside the package (ftc/native_sources.sha256);
# the shipped reference scores and the adaptive checkpoint's key use it.
#   cmake -DFTC_SOURCE_DIR=<checkout> -DFTC_DIGEST_OUT=<file> -P native_sources.cmake
file(GLOB_RECURSE _files RELATIVE "${FTC_SOURCE_DIR}/cpp/plant"
     "${FTC_SOURCE_DIR}/cpp/plant/bindings/*" "${FTC_SOURCE_DIR}/cpp/plant/core/*")
list(SORT _files)
set(_lines "")
foreach(_f IN LISTS _files)
  file(SHA256 "${FTC_SOURCE_DIR}/cpp/plant/${_f}" _h)
  string(APPEND _lines "${_f} ${_h}\n")
endforeach()
string(SHA256 _digest "${_lines}")
file(WRITE "${FTC_DIGEST_OUT}" "${_digest}\n")
