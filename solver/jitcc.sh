# A caching front for CasADi's jit compiler, like ccache (solver/compiled.py runs it with sh).
#
#   sh jitcc.sh CACHE TAG CC ARGS...
#
# CasADi compiles with "CC -O1 -fPIC -c f.c -o f.o" and links with "CC f.o -o f.so -shared".
# The output of either is kept in CACHE under the SHA-256 of TAG (the machine), the arguments
# other than the paths, and the input file's bytes; an identical command later copies it from
# there instead of running CC. CC "-" means no compiler: a command not in the cache fails, and
# the solver interprets that function. A POSIX shell and sha256sum, not Python: CasADi runs this
# about 24 times in a fresh process; a Python front cost 40-200 ms a call, this about 7 ms.
cache=$1 tag=$2 cc=$3
shift 3
out='' input='' flags='' prev=''
for a do
    if [ "$prev" = -o ]; then
        out=$a
    elif [ "$a" != -o ] && [ -f "$a" ]; then
        input=$a
    else
        flags="$flags $a"
    fi
    prev=$a
done
if [ -z "$out" ] || [ -z "$input" ]; then  # not a command this front knows: no cache
    [ "$cc" = - ] && exit 1
    exec "$cc" "$@"
fi
key=$({ printf '%s|%s\n' "$tag" "$flags"; cat "$input"; } | sha256sum) || exit 1
entry="$cache/${key%% *}.${out##*.}"
if [ -f "$entry" ] && cp "$entry" "$out" 2>/dev/null; then
    touch "$entry" 2>/dev/null  # last use, for the pruning of stale entries
    exit 0
fi
if [ "$cc" = - ]; then
    echo "jitcc: $input is not in $cache and there is no compiler" >&2
    exit 1
fi
"$cc" "$@" || exit $?
tmp="$cache/.tmp.$$"
# written whole, then renamed: readers never see a part. Readable by all (CasADi's objects are
# 0600, from mkstemp): the Docker image fills its cache as root and serves as another user;
# a user's own cache stays private by its directory's mode (0700)
if cp "$out" "$tmp" 2>/dev/null && chmod a+r "$tmp" 2>/dev/null; then
    mv -f "$tmp" "$entry" 2>/dev/null || rm -f "$tmp"
else
    rm -f "$tmp" 2>/dev/null
fi
exit 0
