/*
 * The IMU + magnetometer I2C register model (see mpu9150_model.h).
 *
 * Register facts: docs/hardware.md and the parts' own documents — the MPU-6050/9150 and
 * MPU-9250 register maps, the ICM-20948 datasheet (banked registers, REG_BANK_SEL 0x7F), the
 * AK8975 (MS1187-E-02), AK8963 (MS1356-E-02) and AK09916 datasheets. One table per chip and
 * one per magnetometer hold what differs; the behaviour is shared:
 *
 *   chip       IMU WHO_AM_I   PWR_MGMT_1  USER_CTRL  INT_PIN_CFG  TEMP_OUT_H  ACCEL_XOUT_H  magnetometer
 *   MPU-9150   0x75 = 0x68    0x6B        0x6A       0x37         0x41        0x3B          AK8975
 *   MPU-9250   0x75 = 0x71    0x6B        0x6A       0x37         0x41        0x3B          AK8963
 *   MPU-9255   0x75 = 0x73    0x6B        0x6A       0x37         0x41        0x3B          AK8963
 *   ICM-20948  0x00 = 0xEA    0x06        0x03       0x0F         0x39        0x2D          AK09916
 * (the accelerometer's six bytes X, Y, Z high then low, at its reset range of +-2 g)
 *   (the ICM-20948's registers are those of bank 0; REG_BANK_SEL 0x7F bits 5:4 pick the bank)
 *
 *   magnetometer  WIA        ST1   data       ST2    mode register     single self  fuse ROM
 *   AK8975        0x00=0x48  0x02  0x03-0x08  0x09   CNTL 0x0A         0x01   0x08  0x0F, ASA 0x10-0x12
 *   AK8963        0x00=0x48  0x02  0x03-0x08  0x09   CNTL1 0x0A (+BIT) 0x01   0x08  0x0F, ASA 0x10-0x12
 *   AK09916       0x01=0x09  0x10  0x11-0x16  0x18   CNTL2 0x31        0x01   0x10  none
 *
 * The AK8963's CNTL1 bit 4 (BIT) picks 16-bit output (0.15 uT per count, +-32760) over 14-bit
 * (0.6 uT, +-8190); ST2 bit 4 (BITM) mirrors it. AK8963 CNTL2 0x0B and AK09916 CNTL3 0x32
 * bit 0 are soft resets. Only the AK8975 has DERR (a read during a conversion). Continuous
 * measurement modes are not modelled (a mode write that is not power-down, single, self-test
 * or fuse ROM is ignored).
 *
 * Measurements complete lazily: every call that carries a time first settles a measurement
 * whose delay has elapsed, so the model needs no timer of its own. The provider is called with
 * the time the measurement was triggered (the mode register write).
 */
#include "mpu9150_model.h"

#include <string.h>

#define IMU_BYPASS_EN 0x02
#define IMU_I2C_MST_EN 0x20
#define IMU_SLEEP 0x40
#define IMU_DEVICE_RESET 0x80
#define ICM_REG_BANK_SEL 0x7F

/* What WHO_AM_I reads with MPU_FAULT_WRONG_WHOAMI: 0x70, an MPU-6500 (an MPU-9250 without the
 * magnetometer, a part this tool cannot use). Not 0x71: that is a real MPU-9250's id. */
#define WRONG_WHOAMI_VALUE 0x70

#define AK_ADDR 0x0C
#define AK_WIA 0x00
#define AK_WIA_VALUE 0x48
#define AK09916_WIA2_VALUE 0x09
#define AK_ASTC 0x0C
#define AK_ASAX 0x10
#define AK_ASAZ 0x12
#define AK8963_CNTL2 0x0B
#define AK09916_CNTL3 0x32
#define AK09916_TMPS 0x17

#define AK_MODE_POWER_DOWN 0x00
#define AK_BIT_16 0x10 /* AK8963 CNTL1 BIT / ST2 BITM */

#define AK_DRDY 0x01
#define AK_DERR 0x04
#define AK_HOFL 0x08

enum { MAG_AK8975, MAG_AK8963, MAG_AK09916 };

typedef struct {
    uint8_t who_reg, who, pwr_reg, pwr_reset, user_ctrl_reg, int_pin_reg, temp_reg, accel_reg, banked, mag;
} chip_desc;

static const chip_desc CHIPS[MPU_CHIP_COUNT] = {
    [MPU_CHIP_MPU9150] = {0x75, 0x68, 0x6B, IMU_SLEEP, 0x6A, 0x37, 0x41, 0x3B, 0, MAG_AK8975},
    [MPU_CHIP_MPU9250] = {0x75, 0x71, 0x6B, 0x01, 0x6A, 0x37, 0x41, 0x3B, 0, MAG_AK8963},
    [MPU_CHIP_MPU9255] = {0x75, 0x73, 0x6B, 0x01, 0x6A, 0x37, 0x41, 0x3B, 0, MAG_AK8963},
    [MPU_CHIP_ICM20948] = {0x00, 0xEA, 0x06, IMU_SLEEP | 0x01, 0x03, 0x0F, 0x39, 0x2D, 1, MAG_AK09916},
};

typedef struct {
    uint8_t st1, data, st2, cntl, mode_mask, m_single, m_self, m_fuse, has_astc, has_derr;
} mag_desc;

static const mag_desc MAGS[] = {
    [MAG_AK8975] = {0x02, 0x03, 0x09, 0x0A, 0x0F, 0x01, 0x08, 0x0F, 1, 1},
    [MAG_AK8963] = {0x02, 0x03, 0x09, 0x0A, 0x0F, 0x01, 0x08, 0x0F, 1, 0},
    [MAG_AK09916] = {0x10, 0x11, 0x18, 0x31, 0x1F, 0x01, 0x10, 0xFF, 0, 0},
};

enum { DEV_NONE = 0, DEV_MPU, DEV_AK };

struct mpu_model {
    uint8_t mpu_addr;
    int chip;
    const chip_desc *c;
    const mag_desc *g;
    uint8_t bank;            /* ICM-20948 register bank (0 on the others) */
    uint8_t regs[4][128];    /* IMU registers per bank */
    uint8_t asa[3];
    unsigned faults;
    uint32_t measure_us;
    mpu_provider_fn provider;
    void *ctx;

    /* magnetometer state */
    uint8_t ak_mode;    /* the mode bits of the mode register */
    uint8_t ak_bit;     /* AK8963 CNTL1 BIT as last written */
    uint8_t ak_astc;
    uint8_t ak_st1;
    uint8_t ak_st2;     /* HOFL | DERR */
    int16_t ak_data[3];
    int16_t self_test[3]; /* data registers in self-test mode (0 until the host sets them) */
    int measuring;
    uint8_t measuring_mode;
    uint8_t meas_bit;   /* AK8963 BIT of the measurement last triggered */
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

static void imu_reset_registers(mpu_model *m)
{
    memset(m->regs, 0, sizeof m->regs);
    m->bank = 0;
    m->regs[0][m->c->pwr_reg] = m->c->pwr_reset;
}

static void mag_reset(mpu_model *m)
{
    m->ak_mode = AK_MODE_POWER_DOWN;
    m->ak_bit = 0;
    m->ak_astc = 0;
    m->ak_st1 = 0;
    m->ak_st2 = 0;
    memset(m->ak_data, 0, sizeof m->ak_data);
    m->measuring = 0;
    m->meas_bit = 0;
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
    mpu_model_set_chip(m, MPU_CHIP_MPU9150);
}

int mpu_model_set_chip(mpu_model *m, int chip)
{
    if (chip < 0 || chip >= MPU_CHIP_COUNT)
        return -1;
    m->chip = chip;
    m->c = &CHIPS[chip];
    m->g = &MAGS[m->c->mag];
    imu_reset_registers(m);
    mag_reset(m);
    return 0;
}

void mpu_model_set_faults(mpu_model *m, unsigned faults) { m->faults = faults; }

void mpu_model_set_measure_us(mpu_model *m, uint32_t us) { m->measure_us = us; }

int mpu_model_mag_bits(const mpu_model *m)
{
    switch (m->c->mag) {
    case MAG_AK8975: return 13;
    case MAG_AK8963: return m->ak_bit ? 16 : 14; /* a mode write during a measurement is ignored */
    default: return 16;
    }
}

/* The data registers' range at the resolution of the measurement last triggered. */
static int16_t clamp_count(const mpu_model *m, int v)
{
    int lo, hi;
    if (m->c->mag == MAG_AK8975)
        lo = -4096, hi = 4095;
    else if (m->c->mag == MAG_AK09916)
        lo = -32752, hi = 32752;
    else if (m->meas_bit)
        lo = -32760, hi = 32760;
    else
        lo = -8190, hi = 8190;
    if (v < lo) return (int16_t)lo;
    if (v > hi) return (int16_t)hi;
    return (int16_t)v;
}

void mpu_model_set_self_test(mpu_model *m, const int16_t raw[3])
{
    memcpy(m->self_test, raw, sizeof m->self_test); /* clamped when a self-test completes */
}

/* Finish a measurement whose delay has elapsed at time t_us. */
static void settle(mpu_model *m, uint64_t t_us)
{
    if (!m->measuring || (m->faults & MPU_FAULT_STUCK_DRDY) || t_us < m->t_done_us)
        return;
    m->measuring = 0;
    m->ak_mode = AK_MODE_POWER_DOWN; /* single and self-test return to power-down */
    if (m->measuring_mode == m->g->m_self) {
        /* The internal coil's reading: set by the host from its physics (mpu_model_set_self_test),
         * so the one simulator decides what a healthy or a dead coil reads. */
        for (int i = 0; i < 3; i++)
            m->ak_data[i] = clamp_count(m, m->self_test[i]);
        m->ak_st2 &= (uint8_t)~AK_HOFL;
        m->ak_st1 |= AK_DRDY;
        return;
    }
    mpu_measurement meas;
    memset(&meas, 0, sizeof meas);
    if (!m->provider || m->provider(m->ctx, m->t_trigger_us, &meas) != 0)
        return; /* no data: DRDY stays low, as if the measurement never finished */
    m->ak_data[0] = clamp_count(m, meas.hx);
    m->ak_data[1] = clamp_count(m, meas.hy);
    m->ak_data[2] = clamp_count(m, meas.hz);
    if (meas.hofl)
        m->ak_st2 |= AK_HOFL;
    else
        m->ak_st2 &= (uint8_t)~AK_HOFL;
    m->ak_st1 |= AK_DRDY;
    if (!(m->regs[0][m->c->pwr_reg] & IMU_SLEEP)) {
        uint16_t t = (uint16_t)meas.temp_raw;
        m->regs[0][m->c->temp_reg] = (uint8_t)(t >> 8);
        m->regs[0][m->c->temp_reg + 1] = (uint8_t)(t & 0xFF);
        const int16_t a[3] = {meas.ax, meas.ay, meas.az};
        for (int i = 0; i < 3; i++) {
            m->regs[0][m->c->accel_reg + 2 * i] = (uint8_t)((uint16_t)a[i] >> 8);
            m->regs[0][m->c->accel_reg + 2 * i + 1] = (uint8_t)((uint16_t)a[i] & 0xFF);
        }
    }
}

static int ak_reachable(const mpu_model *m)
{
    const uint8_t *r = m->regs[0];
    if (m->faults & MPU_FAULT_NO_AK) return 0;
    if (r[m->c->pwr_reg] & IMU_SLEEP) return 0;
    if (r[m->c->user_ctrl_reg] & IMU_I2C_MST_EN) return 0;
    return (r[m->c->int_pin_reg] & IMU_BYPASS_EN) != 0;
}

/* What a read of a magnetometer register returns, without side effects. */
static uint8_t ak_value(const mpu_model *m, uint8_t reg)
{
    const mag_desc *g = m->g;
    int ak8963 = m->c->mag == MAG_AK8963, ak09916 = m->c->mag == MAG_AK09916;
    int wrong_wia = (m->faults & MPU_FAULT_WRONG_WIA) != 0;
    if (reg == AK_WIA)
        return wrong_wia ? 0x00 : AK_WIA_VALUE;
    if (reg == 0x01) /* AK8975/AK8963 INFO, AK09916 WIA2 */
        return ak09916 && !wrong_wia ? AK09916_WIA2_VALUE : 0x00;
    if (reg == g->st1)
        return m->ak_st1;
    if (reg == g->st2)
        return (uint8_t)(m->ak_st2 | (ak8963 && m->meas_bit ? AK_BIT_16 : 0));
    if (reg == g->cntl)
        return (uint8_t)(m->ak_mode | (ak8963 ? m->ak_bit : 0));
    if (reg >= g->data && reg < g->data + 6) {
        uint16_t v = (uint16_t)m->ak_data[(reg - g->data) / 2];
        return ((reg - g->data) & 1) ? (uint8_t)(v >> 8) : (uint8_t)(v & 0xFF);
    }
    if (g->has_astc && reg == AK_ASTC)
        return m->ak_astc;
    if (g->m_fuse != 0xFF && reg >= AK_ASAX && reg <= AK_ASAZ)
        return m->ak_mode == g->m_fuse ? m->asa[reg - AK_ASAX] : 0x00;
    return 0x00;
}

static uint8_t imu_value(const mpu_model *m, uint8_t reg)
{
    if (reg >= 0x80)
        return 0x00;
    if (m->c->banked && reg == ICM_REG_BANK_SEL)
        return (uint8_t)(m->bank << 4);
    if (m->bank == 0 && reg == m->c->who_reg)
        return (m->faults & MPU_FAULT_WRONG_WHOAMI) ? WRONG_WHOAMI_VALUE : m->c->who;
    return m->regs[m->bank][reg];
}

/* The register a burst moves on to (the parts' automatic increment and wrap-around). */
static uint8_t ak_next(const mpu_model *m, uint8_t reg)
{
    if (m->c->mag == MAG_AK09916) {
        if (reg == 0x03) return 0x10;
        if (reg == 0x18) return 0x00;
        if (reg == 0x32) return 0x30;
        return (uint8_t)(reg + 1);
    }
    if (reg == AK_ASTC) return 0x00;
    if (reg == AK_ASAZ) return AK_ASAX;
    return (uint8_t)(reg + 1);
}

static void ak_mode_write(mpu_model *m, uint8_t v, uint64_t t_us)
{
    const mag_desc *g = m->g;
    uint8_t mode = v & g->mode_mask;
    if (m->measuring) /* a mode write during a measurement is ignored, as on the chip */
        return;
    if (mode == g->m_single || mode == g->m_self) {
        m->ak_mode = mode;
        m->ak_bit = v & AK_BIT_16;
        m->measuring = 1;
        m->measuring_mode = mode;
        m->meas_bit = m->ak_bit;
        m->t_trigger_us = t_us;
        m->t_done_us = t_us + m->measure_us;
    } else if (mode == AK_MODE_POWER_DOWN || mode == g->m_fuse) {
        m->ak_mode = mode;
        m->ak_bit = v & AK_BIT_16;
    }
}

static void ak_write(mpu_model *m, uint8_t reg, uint8_t v, uint64_t t_us)
{
    if (reg == m->g->cntl)
        ak_mode_write(m, v, t_us);
    else if (m->g->has_astc && reg == AK_ASTC)
        m->ak_astc = v & 0x40;
    else if ((m->c->mag == MAG_AK8963 && reg == AK8963_CNTL2) ||
             (m->c->mag == MAG_AK09916 && reg == AK09916_CNTL3)) {
        if (v & 0x01)
            mag_reset(m); /* soft reset */
    }
    /* everything else is read-only (I2CDIS is never honoured: it would brick the model) */
}

static void imu_write(mpu_model *m, uint8_t reg, uint8_t v)
{
    if (reg >= 0x80)
        return;
    if (m->c->banked && reg == ICM_REG_BANK_SEL) {
        m->bank = (v >> 4) & 0x03;
        return;
    }
    if (m->bank == 0) {
        uint8_t t = m->c->temp_reg;
        if (reg == m->c->who_reg || reg == t || reg == t + 1 ||
            (reg >= m->c->accel_reg && reg < m->c->accel_reg + 6)) /* read-only outputs */
            return;
        if (reg == m->c->pwr_reg && (v & IMU_DEVICE_RESET)) {
            imu_reset_registers(m);
            return;
        }
    }
    m->regs[m->bank][reg] = v;
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
            imu_write(m, m->mpu_ptr, byte);
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
            m->ak_ptr = ak_next(m, m->ak_ptr);
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
        *byte = imu_value(m, m->mpu_ptr);
        m->mpu_ptr = (uint8_t)(m->mpu_ptr + 1);
        return 0;
    }
    if (!ak_reachable(m)) {
        *byte = 0xFF;
        return -1;
    }
    uint8_t reg = m->ak_ptr;
    const mag_desc *g = m->g;
    if (reg >= g->data && reg <= g->st2) { /* data (and the AK09916's TMPS) or ST2 */
        if (m->measuring && g->has_derr)
            m->ak_st2 |= AK_DERR; /* read outside the readable window */
        m->ak_st1 &= (uint8_t)~AK_DRDY;
    }
    *byte = ak_value(m, reg);
    if (reg == g->st2)
        m->ak_st2 &= (uint8_t)~AK_DERR; /* reading ST2 releases the error flag */
    m->ak_ptr = ak_next(m, reg);
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
        return imu_value(m, reg);
    if (addr7 == AK_ADDR)
        return ak_value(m, reg);
    return 0xFF;
}
