/* The system calls of a durable file replacement and deletion, each made in one call
 * on a dirty I/O scheduler.
 *
 * Erlang's file module cannot open a directory, so it cannot fsync one: without that
 * a rename is not durable, and after a power cut the new name may be gone while a
 * later write (the sender forgetting its copy of a product) survived. And each of its
 * raw operations is a hand-off to a dirty scheduler of its own: open, write, flush,
 * close, rename and the folder's flush are six. Here they are one, which is what
 * makes a product transfer cost a few microseconds on a RAM disk rather than a few
 * hundred.
 *
 * Each runs on a dirty I/O scheduler, because on a disk a flush blocks for as long as
 * the disk takes, except in a folder held in RAM (tmpfs, ramfs), where nothing waits
 * for a device and the hand-off to another thread would cost more than the work: there
 * the same calls run on the calling scheduler, in microseconds.
 *
 * A process killed during a call on a dirty scheduler is gone at once, but the call
 * runs on to its end. So every replacement and deletion is entered, while it runs, in
 * a table of files being written, and a reader first waits until its file is not in
 * it: a task restarted after a crash reads what its last incarnation wrote, not the
 * file as it was a moment before that write landed. */
#include <erl_nif.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <string.h>
#include <unistd.h>
#ifdef __linux__
#include <sys/vfs.h>
#define TMPFS_MAGIC_ 0x01021994UL
#define RAMFS_MAGIC_ 0x858458f6UL
#endif

/* The files being written: a slot per write under way. There are never more writes
 * under way than scheduler threads; a write finding the table full waits for a slot. */
#define IN_FLIGHT_MAX 256
static ErlNifMutex *flight_lock;
static ErlNifCond *flight_change;
static char *in_flight[IN_FLIGHT_MAX];

static int flying(const char *path)
{
    int i;

    for (i = 0; i < IN_FLIGHT_MAX; i++)
        if (in_flight[i] != NULL && strcmp(in_flight[i], path) == 0)
            return 1;
    return 0;
}

/* Enters a path in the table; the slot it took, or -1 without memory. */
static int flight_begin(const char *path)
{
    size_t len = strlen(path) + 1;
    char *copy = enif_alloc(len);
    int i;

    if (copy == NULL)
        return -1;
    memcpy(copy, path, len);
    enif_mutex_lock(flight_lock);
    for (;;) {
        for (i = 0; i < IN_FLIGHT_MAX; i++)
            if (in_flight[i] == NULL) {
                in_flight[i] = copy;
                enif_mutex_unlock(flight_lock);
                return i;
            }
        enif_cond_wait(flight_change, flight_lock);
    }
}

static void flight_end(int slot)
{
    char *copy;

    if (slot < 0)
        return;
    enif_mutex_lock(flight_lock);
    copy = in_flight[slot];
    in_flight[slot] = NULL;
    enif_cond_broadcast(flight_change);
    enif_mutex_unlock(flight_lock);
    enif_free(copy);
}

/* Errors named as Erlang's file module names them. */
static const char *errno_name(int err)
{
    switch (err) {
    case ENOENT: return "enoent";
    case ENOTDIR: return "enotdir";
    case EISDIR: return "eisdir";
    case EEXIST: return "eexist";
    case ENOTEMPTY: return "enotempty";
    case EXDEV: return "exdev";
    case EBUSY: return "ebusy";
    case EACCES: return "eacces";
    case EPERM: return "eperm";
    case EIO: return "eio";
    case EROFS: return "erofs";
    case ENOSPC: return "enospc";
    case EDQUOT: return "edquot";
    case EFBIG: return "efbig";
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

static ERL_NIF_TERM error2(ErlNifEnv *env, const char *where, int err)
{
    return enif_make_tuple2(env, enif_make_atom(env, "error"),
                            enif_make_tuple2(env, enif_make_atom(env, where),
                                             enif_make_atom(env, errno_name(err))));
}

/* A path argument as a NUL-terminated string; false if it is not one. */
static int get_path(ErlNifEnv *env, ERL_NIF_TERM term, char *buf, size_t size)
{
    ErlNifBinary bin;

    if (!enif_inspect_iolist_as_binary(env, term, &bin) || bin.size == 0 ||
        bin.size >= size || memchr(bin.data, 0, bin.size) != NULL)
        return 0;
    memcpy(buf, bin.data, bin.size);
    buf[bin.size] = '\0';
    return 1;
}

static int get_bool(ErlNifEnv *env, ERL_NIF_TERM term, int *value)
{
    char atom[6];

    if (!enif_get_atom(env, term, atom, sizeof atom, ERL_NIF_LATIN1))
        return 0;
    if (strcmp(atom, "true") == 0)
        *value = 1;
    else if (strcmp(atom, "false") == 0)
        *value = 0;
    else
        return 0;
    return 1;
}

/* fsync(2) of a folder; 0 or an errno. */
static int sync_dir(const char *dir)
{
    int fd, rc, err = 0;

    do { fd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC); } while (fd < 0 && errno == EINTR);
    if (fd < 0)
        return errno;
    do { rc = fsync(fd); } while (rc < 0 && errno == EINTR);
    if (rc < 0)
        err = errno;
    close(fd);
    return err;
}

/* The folder a path is in: "." for a bare name, "/" for a name at the root. */
static void parent_of(const char *path, char *dir, size_t size)
{
    const char *slash = strrchr(path, '/');
    size_t len;

    if (slash == NULL) {
        strcpy(dir, ".");
        return;
    }
    len = slash == path ? 1 : (size_t)(slash - path);
    if (len >= size)
        len = size - 1;
    memcpy(dir, path, len);
    dir[len] = '\0';
}

static int write_all(int fd, const unsigned char *data, size_t size)
{
    while (size > 0) {
        ssize_t n = write(fd, data, size);
        if (n < 0) {
            if (errno == EINTR)
                continue;
            return errno;
        }
        data += n;
        size -= (size_t)n;
    }
    return 0;
}

static ERL_NIF_TERM fsync_dir(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char dir[PATH_MAX];
    int err;

    (void)argc;
    if (!get_path(env, argv[0], dir, sizeof dir))
        return enif_make_badarg(env);
    err = sync_dir(dir);
    if (err != 0)
        return enif_make_tuple2(env, enif_make_atom(env, "error"),
                                enif_make_atom(env, errno_name(err)));
    return enif_make_atom(env, "ok");
}

/* replace(Tmp, Path, Data, Sync): Data is written to Tmp, flushed (Sync), renamed over
 * Path, and Path's folder flushed (Sync). ok, or {error, {Where, Posix}} with Where
 * one of write, rename, dir; after an error Tmp is gone. */
static ERL_NIF_TERM replace_in(ErlNifEnv *env, const char *tmp, const char *path,
                               ErlNifBinary data, int sync);

static ERL_NIF_TERM replace(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char tmp[PATH_MAX], path[PATH_MAX];
    ErlNifBinary data;
    ERL_NIF_TERM result;
    int sync, slot;

    (void)argc;
    if (!get_path(env, argv[0], tmp, sizeof tmp) || !get_path(env, argv[1], path, sizeof path) ||
        !enif_inspect_iolist_as_binary(env, argv[2], &data) || !get_bool(env, argv[3], &sync))
        return enif_make_badarg(env);
    slot = flight_begin(path);
    result = replace_in(env, tmp, path, data, sync);
    flight_end(slot);
    return result;
}

static ERL_NIF_TERM replace_in(ErlNifEnv *env, const char *tmp, const char *path,
                               ErlNifBinary data, int sync)
{
    char dir[PATH_MAX];
    int fd, err = 0;

    do {
        fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    } while (fd < 0 && errno == EINTR);
    if (fd < 0)
        return error2(env, "write", errno);
    err = write_all(fd, data.data, data.size);
    if (err == 0 && sync && fdatasync(fd) < 0)
        err = errno;
    if (close(fd) < 0 && err == 0 && errno != EINTR)
        err = errno;
    if (err != 0) {
        unlink(tmp);
        return error2(env, "write", err);
    }
    if (rename(tmp, path) < 0) {
        err = errno;
        unlink(tmp);
        return error2(env, "rename", err);
    }
    if (sync) {
        parent_of(path, dir, sizeof dir);
        err = sync_dir(dir);
        if (err != 0)
            return error2(env, "dir", err);
    }
    return enif_make_atom(env, "ok");
}

/* remove(Path, Sync): Path is deleted (a missing one is no error) and its folder
 * flushed (Sync). ok, or {error, {Where, Posix}} with Where one of delete, dir. */
static ERL_NIF_TERM remove_in(ErlNifEnv *env, const char *path, int sync);

static ERL_NIF_TERM remove_file(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char path[PATH_MAX];
    ERL_NIF_TERM result;
    int sync, slot;

    (void)argc;
    if (!get_path(env, argv[0], path, sizeof path) || !get_bool(env, argv[1], &sync))
        return enif_make_badarg(env);
    slot = flight_begin(path);
    result = remove_in(env, path, sync);
    flight_end(slot);
    return result;
}

static ERL_NIF_TERM remove_in(ErlNifEnv *env, const char *path, int sync)
{
    char dir[PATH_MAX];
    int err;

    if (unlink(path) < 0) {
        if (errno == ENOENT)
            return enif_make_atom(env, "ok");
        return error2(env, "delete", errno);
    }
    if (sync) {
        parent_of(path, dir, sizeof dir);
        err = sync_dir(dir);
        if (err != 0)
            return error2(env, "dir", err);
    }
    return enif_make_atom(env, "ok");
}

/* writing(Path): whether a replacement or deletion of Path is under way. */
static ERL_NIF_TERM writing(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char path[PATH_MAX];
    int busy;

    (void)argc;
    if (!get_path(env, argv[0], path, sizeof path))
        return enif_make_badarg(env);
    enif_mutex_lock(flight_lock);
    busy = flying(path);
    enif_mutex_unlock(flight_lock);
    return enif_make_atom(env, busy ? "true" : "false");
}

/* settle(Path): returns once no replacement or deletion of Path is under way. */
static ERL_NIF_TERM settle(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char path[PATH_MAX];

    (void)argc;
    if (!get_path(env, argv[0], path, sizeof path))
        return enif_make_badarg(env);
    enif_mutex_lock(flight_lock);
    while (flying(path))
        enif_cond_wait(flight_change, flight_lock);
    enif_mutex_unlock(flight_lock);
    return enif_make_atom(env, "ok");
}

/* in_ram(Dir): {ok, Bool}, whether a folder's file system is held in RAM. */
static ERL_NIF_TERM in_ram(ErlNifEnv *env, int argc, const ERL_NIF_TERM argv[])
{
    char dir[PATH_MAX];
    int ram = 0;

    (void)argc;
    if (!get_path(env, argv[0], dir, sizeof dir))
        return enif_make_badarg(env);
#ifdef __linux__
    {
        struct statfs fs;
        if (statfs(dir, &fs) < 0)
            return enif_make_tuple2(env, enif_make_atom(env, "error"),
                                    enif_make_atom(env, errno_name(errno)));
        ram = (unsigned long)fs.f_type == TMPFS_MAGIC_ || (unsigned long)fs.f_type == RAMFS_MAGIC_;
    }
#endif
    return enif_make_tuple2(env, enif_make_atom(env, "ok"),
                            enif_make_atom(env, ram ? "true" : "false"));
}

static ErlNifFunc funcs[] = {
    {"fsync_dir", 1, fsync_dir, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"replace_nif", 4, replace, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"remove_nif", 2, remove_file, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"replace_ram_nif", 4, replace, 0},
    {"remove_ram_nif", 2, remove_file, 0},
    {"in_ram_nif", 1, in_ram, ERL_NIF_DIRTY_JOB_IO_BOUND},
    {"writing_nif", 1, writing, 0},
    {"settle_nif", 1, settle, ERL_NIF_DIRTY_JOB_IO_BOUND}
};

static int load(ErlNifEnv *env, void **priv_data, ERL_NIF_TERM load_info)
{
    (void)env;
    (void)priv_data;
    (void)load_info;
    flight_lock = enif_mutex_create("cell_file_in_flight");
    flight_change = enif_cond_create("cell_file_in_flight");
    return flight_lock == NULL || flight_change == NULL;
}

ERL_NIF_INIT(cell_file, funcs, load, NULL, NULL, NULL)
