#!/usr/bin/env bash
# Make sure a system libLLVM >= 16 exists for Dr.Jit's LLVM backend.
# Prints the library path on success. Installs Debian's libllvm19 when running as root.
set -euo pipefail
find_llvm() {
    for dir in /usr/lib/x86_64-linux-gnu /usr/lib/aarch64-linux-gnu /usr/lib /usr/local/lib /usr/lib64; do
        for v in 21 20 19 18 17 16; do
            for f in "$dir/libLLVM-$v.so" "$dir/libLLVM.so.$v.1" "$dir/libLLVM-$v.so.1" "$dir/llvm-$v/lib/libLLVM.so"; do
                [ -e "$f" ] && { echo "$f"; return 0; }
            done
        done
    done
    return 1
}
if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -e "$DRJIT_LIBLLVM_PATH" ]; then echo "$DRJIT_LIBLLVM_PATH"; exit 0; fi
if find_llvm; then exit 0; fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "gdpt: installing libllvm19 (Dr.Jit's LLVM backend needs libLLVM >= 16)" >&2
    apt-get update -qq >&2 && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >&2
    find_llvm && exit 0
fi
echo "gdpt: no libLLVM >= 16 found. Install it (Debian/Ubuntu: 'apt-get install libllvm19') or set DRJIT_LIBLLVM_PATH." >&2
exit 1
