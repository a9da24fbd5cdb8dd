/*
 * MPU-9150 + AK8975 I2C register model (see mpu9150_model.h).
 *
 * Register facts: docs/hardware.md, from the AK8975 datasheet
 * (MS1187-E-02) and the MPU-6050/9150 register maps.
 *
 * Measurements complete lazily: every call that carries a time first settles a measurement
 * whose delay has elapsed, so the model needs no timer of its own. The provider is called with
 * the time the measurement was triggered (the CNTL write).
 */
#include "mpu9150_model.h"

#include <string.h>

/* MPU-9150 registers */
#define MPU_INT_PIN_CFG 0x37
#define MPU_TEMP_OUT_H 0x41
#define MPU_TEMP_OUT_L 0x42
#define MPU_USER_CTRL 0x6A
#define MPU_PWR_MGMT_1 0x6B
#define MPU_WHO_AM_I 0x75

#define MPU_BYPASS_EN 0x02
#define MPU_I2C_MST_EN 0x20
#define MPU_SLEEP 0x40
#define MPU_DEVICE_RESET 0x80

/* AK8975 registers */
#define AK_ADDR 0x0C
#define AK_WIA 0x00
#define AK_INFO 0x01
#define AK_ST1 0x02
#define AK_HXL 0x03
#define AK_ST2 0x09
#define AK_CNTL 0x0A
#define AK_ASTC 0x0C
#define AK_ASAX 0x10
#define AK_ASAZ 0x12

#define AK_MODE_POWER_DOWN 0x00
#define AK_MODE_SINGLE 0x01
#define AK_MODE_SELF_TEST 0x08
#define AK_MODE_FUSE_ROM 0x0F

#define AK_DRDY 0x01
#define AK_DERR 0x04
#define AK_HOFL 0x08

enum { DEV_NONE = 0, DEV_MPU, DEV_AK };

struct mpu_model {
    uint8_t mpu_addr;
    uint8_t mpu[256];
    uint8_t asa[3];
    unsigned faults;
    uint32_t measure_us;
    mpu_provider_fn provider;
    void *ctx;

    /* AK8975 state */
    uint8_t ak_mode;    /* CNTL */
    uint8_t ak_astc;
    uint8_t ak_st1;
    uint8_t ak_st2;     /* HOFL | DERR */
    int16_t ak_data[3];
    int16_t self_test[3]; /* data registers in self-test mode (0 until the host sets them) */
    int measuring;
    uint8_t measuring_mode;
    uint64_t t_trigger_us;
    uint64_t t_done_us;

    /* current transaction */
    int dev;
    int is_read;
    int have_pointer;
    uint8_t mpu_ptr;
    uint8_t ak_ptr;
};

size_t mpu_model_size(void) { return sizeof(struct mpu_model); }

static void mpu_reset_registers(mpu_model *m)
{
    memset(m->mpu, 0, sizeof m->mpu);
    m->mpu[MPU_PWR_MGMT_1] = MPU_SLEEP;
    m->mpu[MPU_WHO_AM_I] = 0x68;
}

void mpu_model_init(mpu_model *m, uint8_t mpu_addr, const uint8_t asa[3],
                    mpu_provider_fn provider, void *ctx)
{
    memset(m, 0, sizeof *m);
    m->mpu_addr = mpu_addr;
    if (asa)
        memcpy(m->asa, asa, 3);
    else
        m->asa[0] = m->asa[1] = m->asa[2] = 128;
    m->provider = provider;
    m->ctx = ctx;
    m->measure_us = 7300;
    mpu_reset_registers(m);
}

void mpu_model_set_faults(mpu_model *m, unsigned faults) { m->faults = faults; }

void mpu_model_set_measure_us(mpu_model *m, uint32_t us) { m->measure_us = us; }

static int16_t clamp_count(int v)
{
    if (v < -4096) return -4096;
    if (v > 4095) return 4095;
    return (int16_t)v;
}

void mpu_model_set_self_test(mpu_model *m, const int16_t raw[3])
{
    for (int i = 0; i < 3; i++)
        m->self_test[i] = clamp_count(raw[i]);
}

/* Finish a measurement whose delay has elapsed at time t_us. */
static void settle(mpu_model *m, uint64_t t_us)
{
    if (!m->measuring || (m->faults & MPU_FAULT_STUCK_DRDY) || t_us < m->t_done_us)
        return;
    m->measuring = 0;
    m->ak_mode = AK_MODE_POWER_DOWN; /* single and self-test return to power-down */
    if (m->measuring_mode == AK_MODE_SELF_TEST) {
        /* The internal coil's reading: set by the host from its physics (mpu_model_set_self_test),
         * so the one simulator decides what a healthy or a dead coil reads. */
        for (int i = 0; i < 3; i++)
            m->ak_data[i] = m->self_test[i];
        m->ak_st2 &= (uint8_t)~AK_HOFL;
        m->ak_st1 |= AK_DRDY;
        return;
    }
    mpu_measurement meas;
    memset(&meas, 0, sizeof meas);
    if (!m->provider || m->provider(m->ctx, m->t_trigger_us, &meas) != 0)
        return; /* no data: DRDY stays low, as if the measurement never finished */
    m->ak_data[0] = clamp_count(meas.hx);
    m->ak_data[1] = clamp_count(meas.hy);
    m->ak_data[2] = clamp_count(meas.hz);
    if (meas.hofl)
        m->ak_st2 |= AK_HOFL;
    else
        m->ak_st2 &= (uint8_t)~AK_HOFL;
    m->ak_st1 |= AK_DRDY;
    if (!(m->mpu[MPU_PWR_MGMT_1] & MPU_SLEEP)) {
        uint16_t t = (uint16_t)meas.temp_raw;
        m->mpu[MPU_TEMP_OUT_H] = (uint8_t)(t >> 8);
        m->mpu[MPU_TEMP_OUT_L] = (uint8_t)(t & 0xFF);
    }
}

static int ak_reachable(const mpu_model *m)
{
    if (m->faults & MPU_FAULT_NO_AK) return 0;
    if (m->mpu[MPU_PWR_MGMT_1] & MPU_SLEEP) return 0;
    if (m->mpu[MPU_USER_CTRL] & MPU_I2C_MST_EN) return 0;
    return (m->mpu[MPU_INT_PIN_CFG] & MPU_BYPASS_EN) != 0;
}

/* What a read of an AK8975 register returns, without side effects. */
static uint8_t ak_value(const mpu_model *m, uint8_t reg)
{
    switch (reg) {
    case AK_WIA: return (m->faults & MPU_FAULT_WRONG_WIA) ? 0x00 : 0x48;
    case AK_INFO: return 0x00;
    case AK_ST1: return m->ak_st1;
    case AK_ST2: return m->ak_st2;
    case AK_CNTL: return m->ak_mode;
    case AK_ASTC: return m->ak_astc;
    default: break;
    }
    if (reg >= AK_HXL && reg < AK_ST2) {
        uint16_t v = (uint16_t)m->ak_data[(reg - AK_HXL) / 2];
        return ((reg - AK_HXL) & 1) ? (uint8_t)(v >> 8) : (uint8_t)(v & 0xFF);
    }
    if (reg >= AK_ASAX && reg <= AK_ASAZ)
        return m->ak_mode == AK_MODE_FUSE_ROM ? m->asa[reg - AK_ASAX] : 0x00;
    return 0x00;
}

static uint8_t mpu_value(const mpu_model *m, uint8_t reg)
{
    if (reg == MPU_WHO_AM_I)
        return (m->faults & MPU_FAULT_WRONG_WHOAMI) ? 0x71 : 0x68;
    return m->mpu[reg];
}

static uint8_t ak_next(uint8_t reg)
{
    if (reg == AK_ASTC) return 0x00;
    if (reg == AK_ASAZ) return AK_ASAX;
    return (uint8_t)(reg + 1);
}

static void ak_write(mpu_model *m, uint8_t reg, uint8_t v, uint64_t t_us)
{
    if (reg == AK_CNTL) {
        uint8_t mode = v & 0x0F;
        if (m->measuring) /* a mode write during a measurement is ignored, as on the chip */
            return;
        if (mode == AK_MODE_SINGLE || mode == AK_MODE_SELF_TEST) {
            m->ak_mode = mode;
            m->measuring = 1;
            m->measuring_mode = mode;
            m->t_trigger_us = t_us;
            m->t_done_us = t_us + m->measure_us;
        } else if (mode == AK_MODE_POWER_DOWN || mode == AK_MODE_FUSE_ROM) {
            m->ak_mode = mode;
        }
    } else if (reg == AK_ASTC) {
        m->ak_astc = v & 0x40;
    }
    /* everything else is read-only (I2CDIS is never honoured: it would brick the model) */
}

static void mpu_write(mpu_model *m, uint8_t reg, uint8_t v)
{
    if (reg == MPU_WHO_AM_I || reg == MPU_TEMP_OUT_H || reg == MPU_TEMP_OUT_L)
        return;
    if (reg == MPU_PWR_MGMT_1 && (v & MPU_DEVICE_RESET)) {
        mpu_reset_registers(m);
        return;
    }
    m->mpu[reg] = v;
}

int mpu_model_start(mpu_model *m, uint8_t addr7, int is_read, uint64_t t_us)
{
    settle(m, t_us);
    m->dev = DEV_NONE;
    if (addr7 == m->mpu_addr)
        m->dev = DEV_MPU;
    else if (addr7 == AK_ADDR && ak_reachable(m))
        m->dev = DEV_AK;
    if (m->dev == DEV_NONE)
        return -1;
    m->is_read = is_read ? 1 : 0;
    m->have_pointer = 0;
    return 0;
}

int mpu_model_write(mpu_model *m, uint8_t byte, uint64_t t_us)
{
    settle(m, t_us);
    if (m->dev == DEV_NONE || m->is_read)
        return -1;
    if (m->dev == DEV_MPU) {
        if (!m->have_pointer) {
            m->mpu_ptr = byte;
            m->have_pointer = 1;
        } else {
            mpu_write(m, m->mpu_ptr, byte);
            m->mpu_ptr = (uint8_t)(m->mpu_ptr + 1);
        }
    } else {
        if (!ak_reachable(m))
            return -1;
        if (!m->have_pointer) {
            m->ak_ptr = byte;
            m->have_pointer = 1;
        } else {
            ak_write(m, m->ak_ptr, byte, t_us);
            m->ak_ptr = ak_next(m->ak_ptr);
        }
    }
    return 0;
}

int mpu_model_read(mpu_model *m, uint8_t *byte, uint64_t t_us)
{
    settle(m, t_us);
    if (m->dev == DEV_NONE || !m->is_read) {
        *byte = 0xFF;
        return -1;
    }
    if (m->dev == DEV_MPU) {
        *byte = mpu_value(m, m->mpu_ptr);
        m->mpu_ptr = (uint8_t)(m->mpu_ptr + 1);
        return 0;
    }
    if (!ak_reachable(m)) {
        *byte = 0xFF;
        return -1;
    }
    uint8_t reg = m->ak_ptr;
    if (reg >= AK_HXL && reg <= AK_ST2) {
        if (m->measuring)
            m->ak_st2 |= AK_DERR; /* read outside the readable window */
        m->ak_st1 &= (uint8_t)~AK_DRDY;
    }
    *byte = ak_value(m, reg);
    if (reg == AK_ST2)
        m->ak_st2 &= (uint8_t)~AK_DERR; /* reading ST2 releases the error flag */
    m->ak_ptr = ak_next(reg);
    return 0;
}

void mpu_model_stop(mpu_model *m, uint64_t t_us)
{
    settle(m, t_us);
    m->dev = DEV_NONE;
    m->have_pointer = 0;
}

uint8_t mpu_model_peek(const mpu_model *m, uint8_t addr7, uint8_t reg)
{
    if (addr7 == m->mpu_addr)
        return mpu_value(m, reg);
    if (addr7 == AK_ADDR)
        return ak_value(m, reg);
    return 0xFF;
}
