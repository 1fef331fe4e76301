#!/usr/bin/env bash
# The C kernels built with AddressSanitizer and UBSan (into their own cache folder, so the normal builds stay),
# then the kernel tests and the kernel fuzz run against them; any sanitizer report fails the run.
#   tests/sanitize/run.sh                 # tests/core/test_kernels.py, test_kernel_fuzz.py, geometry/test_ransac_kernel.py
#   tests/sanitize/run.sh tests/depth/test_dense.py -k kernel   # other pytest arguments instead
set -euo pipefail
cd "$(dirname "$0")/../.."
compiler=${CC:-gcc}
asan=$("$compiler" -print-file-name=libasan.so)
ubsan=$("$compiler" -print-file-name=libubsan.so)
[ -f "$asan" ] || { echo "sanitize: $compiler has no libasan.so ($asan)" >&2; exit 2; }
log=$(mktemp -d)
export SVS_TORCH_CACHE=${SVS_TORCH_SANITIZE_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/svs_torch-sanitize}
export SVS_TORCH_CFLAGS_EXTRA="-fsanitize=address,undefined,float-cast-overflow -fno-sanitize-recover=undefined -fno-omit-frame-pointer -g"
# The sanitizer runtimes must be loaded before python; torch and python leak by design (no leak check).
export LD_PRELOAD="$asan $ubsan${LD_PRELOAD:+ $LD_PRELOAD}"
export ASAN_OPTIONS="detect_leaks=0:abort_on_error=1:log_path=$log/asan"
export UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1:log_path=$log/ubsan"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
[ $# -gt 0 ] || set -- tests/core/test_kernels.py tests/core/test_kernel_fuzz.py tests/geometry/test_ransac_kernel.py
status=0
python -m pytest -q -p no:cacheprovider "$@" || status=$?
if compgen -G "$log/*" > /dev/null; then
    echo "sanitize: reports in $log:" >&2
    head -n 40 "$log"/* >&2
    exit 1
fi
rm -rf "$log"
exit "$status"
