/* fsync(2) of a directory, which Erlang's file module cannot open. Without it a
 * rename is not durable: after a power cut the new name may be gone while a later
 * write (the sender forgetting its copy of a product) survived. Runs on a dirty I/O
 * scheduler because fsync blocks for as long as the disk takes. */
#include <erl_nif.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <string.h>
#include <unistd.h>

/* The errors open(2) and fsync(2) can give, named as Erlang's file module names them. */
static const char *errno_name(int err)
{
    switch (err) {
    case ENOENT: return "enoent";
    case ENOTDIR: return "enotdir";
    case EACCES: return "eacces";
    case EPERM: return "eperm";
    case EIO: return "eio";
    case EROFS: return "erofs";
    case ENOSPC: return "enospc";
    case EDQUOT: return "edquot";
    case ELOOP: return "eloop";
    case ENAMETOOLONG: return "enametoolong";
    case EMFILE: return "emfile";
    case ENFILE: return "enfile";
    case ENOMEM: return "enomem";
    case EBADF: return "ebadf";
    case EINVAL: return "einval";
    default: return "eunknown";
    }
}

static ERL_NIF_TERM error_tuple(ErlNifEnv *env, int err)
{
    return enif_make_tuple2(env, enif_make_atom(env, "error"),
                            enif_make_atom(env, errno_name(err)));
}

static ERL_NIF_TERM fsync_dir(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    ErlNifBinary path;
    char buf[PATH_MAX];
    int fd, rc;

    (void)argc;
    if (!enif_inspect_iolist_as_binary(env, argv[0], &path) || path.size == 0 ||
        path.size >= sizeof buf || memchr(path.data, 0, path.size) != NULL)
        return enif_make_badarg(env);
    memcpy(buf, path.data, path.size);
    buf[path.size] = '\0';

    do { fd = open(buf, O_RDONLY | O_DIRECTORY | O_CLOEXEC); } while (fd < 0 && errno == EINTR);
    if (fd < 0)
        return error_tuple(env, errno);
    do { rc = fsync(fd); } while (rc < 0 && errno == EINTR);
    if (rc < 0) {
        int err = errno;
        close(fd);
        return error_tuple(env, err);
    }
    close(fd);
    return enif_make_atom(env, "ok");
}

static ErlNifFunc funcs[] = {
    {"fsync_dir", 1, fsync_dir, ERL_NIF_DIRTY_JOB_IO_BOUND}
};

ERL_NIF_INIT(cell_file, funcs, NULL, NULL, NULL, NULL)
